// benchctl console page: live view over a WebSocket, controls over JSON POSTs. The token comes from this page's URL
// and goes with every request as a header (and in the socket's URL), never as a cookie: cookies ignore ports, so
// every other web server on this computer would receive it.
"use strict";
const $ = (id) => document.getElementById(id);
const TOKEN = new URLSearchParams(location.search).get("token") || "";
const COLOURS = ["#ff5050", "#40d060", "#5090ff"];
let info = null;
let socket = null;
let frames = 0;
let lastSeq = 0;
let drawnSeq = 0;
let zoomUrl = null;
let shownFrame = null;
let laserState = {};

function say(text) { const pre = $("events"); pre.textContent = text + "\n" + pre.textContent; }

async function api(path, body, raw) {
  const options = { method: body === undefined ? "GET" : "POST", credentials: "omit",
    headers: { "x-benchctl-token": TOKEN } };
  if (body !== undefined) {
    options.body = raw ? body : JSON.stringify(body);
    options.headers["content-type"] = raw ? "application/octet-stream" : "application/json";
  }
  const response = await fetch(path, options);
  const data = await response.json().catch(() => ({ error: `HTTP ${response.status}` }));
  if (!response.ok || data.error) { say("error: " + (data.error || response.status)); throw new Error(data.error); }
  return data;
}

function option(select, value, text) {
  const o = document.createElement("option"); o.value = value; o.textContent = text || value; select.appendChild(o);
}

async function init() {
  $("report").href = "/api/procedures/report?token=" + encodeURIComponent(TOKEN);
  info = await api("/api/info");
  $("profile").textContent = "profile " + info.profile;
  if (info.deadman_s) $("deadman").textContent = `(emission off ${info.deadman_s} s after the page goes away)`;
  const body = $("laser").querySelector("tbody");
  for (const ch of info.channels) {
    option($("channel"), ch.name, `${ch.name} (${ch.wavelength_nm} nm)`);
    const row = document.createElement("tr");
    row.id = "laser-" + ch.name;
    row.innerHTML = `<td class="ch-${ch.name}">${ch.name}<br><span class="muted small">${ch.wavelength_nm} nm<br>≤ ${ch.limit_mw} mW</span></td>
      <td><input class="setpoint" value="${ch.setpoint_mw}mW" title="e.g. 2mW, 0.5mW or 5%"></td>
      <td><button class="set">set</button></td><td><button class="emit">off</button></td>
      <td class="small"><span class="readback"></span><br><span class="status"></span></td>`;
    row.querySelector(".set").onclick = () => api(`/api/laser/${ch.name}/power`,
      { power: row.querySelector(".setpoint").value }).then((r) => say(`${ch.name}: setpoint ${r.setpoint_mw} mW (read back)`), () => {});
    row.querySelector(".emit").onclick = () => {
      const on = !(laserState[ch.name] && laserState[ch.name].emission);
      api(`/api/laser/${ch.name}/emission`, { on }).catch(() => {});
    };
    body.appendChild(row);
  }
  for (const t of info.targets) option($("target"), t);
  for (const m of info.methods) option($("method"), m);
  for (const c of info.checkpoints) option($("checkpoint"), c);
  for (const p of info.procedures) option($("procedure"), p);
  for (const z of info.zernike) {
    const label = document.createElement("label");
    label.innerHTML = `${z.replace("_", " ")} <input type="number" step="0.05" value="0" data-term="${z}">`;
    $("zernike").appendChild(label);
  }
  showFields();
  connect();
  setInterval(() => send("heartbeat"), 1000);
}

function showFields() {
  const kind = $("kind").value;
  for (const el of document.querySelectorAll("[data-for]")) {
    el.hidden = !(el.dataset.for === kind || (el.dataset.for === "hologram" && kind === "hologram"));
  }
  $("channel").parentElement.hidden = kind === "blank";
  $("zernike-box").hidden = kind === "blank";
}

function connect() {
  socket = new WebSocket(`ws://${location.host}/ws?token=${encodeURIComponent(TOKEN)}`);
  socket.binaryType = "arraybuffer";
  socket.onopen = () => { $("link").textContent = "connected"; $("link").className = "badge on"; drawnSeq = 0; found(); };
  socket.onclose = () => {
    $("link").textContent = "disconnected"; $("link").className = "badge off";
    lost();
    setTimeout(connect, 1000);
  };
  socket.onmessage = (event) => {
    if (typeof event.data === "string") {
      send("heartbeat");
      const message = JSON.parse(event.data);
      if ("all_off" in message) allOffAnswered(message.all_off); else state(message);
    }
    else frame(event.data).then((seq) => send("ack " + seq), () => send("ack " + lastSeq));
  };
}

// A page that has lost its console knows nothing of the bench: every control is greyed out and the laser's state is
// said to be unknown (the console switches emission off when it stops, but it may have stopped without doing so).
function lost() {
  if (document.body.classList.contains("lost")) return;
  document.body.classList.add("lost");
  $("lost").hidden = false;
  for (const control of document.querySelectorAll("button, input, select")) {
    control.dataset.before = control.disabled ? "disabled" : "";
    control.disabled = true;
  }
  for (const row of document.querySelectorAll("#laser tbody tr")) {
    const emit = row.querySelector(".emit");
    emit.textContent = "?"; emit.className = "emit";
    row.querySelector(".readback").textContent = "unknown";
    row.querySelector(".status").textContent = "";
  }
  $("fps").textContent = "0";
}

function found() {
  if (!document.body.classList.contains("lost")) return;
  document.body.classList.remove("lost");
  $("lost").hidden = true;
  for (const control of document.querySelectorAll("button, input, select")) control.disabled = control.dataset.before === "disabled";
}

// Every message to the server is a heartbeat for the laser's dead-man switch: the page answers what the server
// sends (state twice a second, frames), so it needs no timer of its own; the interval is a second line.
function send(text) { if (socket && socket.readyState === 1) socket.send(text); }

async function frame(buffer) {
  const view = new DataView(buffer);
  const length = view.getUint32(0);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, length)));
  lastSeq = header.seq;
  const zoomBytes = header.zoom_bytes;
  const jpeg = new Blob([new Uint8Array(buffer, 4 + length, buffer.byteLength - 4 - length - zoomBytes)],
    { type: "image/jpeg" });
  const bitmap = await createImageBitmap(jpeg);
  if (header.seq < drawnSeq) { bitmap.close(); return header.seq; }  // a newer one was drawn meanwhile
  drawnSeq = header.seq;
  const canvas = $("frame");
  if (canvas.width !== bitmap.width || canvas.height !== bitmap.height) {
    canvas.width = $("overlay").width = bitmap.width; canvas.height = $("overlay").height = bitmap.height;
    $("frame-box").style.setProperty("--aspect", bitmap.width / bitmap.height);
  }
  canvas.getContext("2d").drawImage(bitmap, 0, 0);
  bitmap.close();
  if (zoomBytes) {
    const zoom = new Blob([new Uint8Array(buffer, buffer.byteLength - zoomBytes)], { type: "image/jpeg" });
    if (zoomUrl) URL.revokeObjectURL(zoomUrl);
    zoomUrl = URL.createObjectURL(zoom);
    $("zoom").src = zoomUrl; $("zoom-box").hidden = false;
    const w = header.zoom_window;
    $("zoom-caption").textContent = w ? `1:1 · rows ${w[0]}–${w[0] + w[2]}, cols ${w[1]}–${w[1] + w[3]}` : "1:1";
  } else { $("zoom-box").hidden = true; }
  frames += 1;
  $("frame-count").textContent = frames;
  overlay(header);
  statistics(header.stats);
  return header.seq;
}

const CHANNEL_COLOURS = { red: "#ff6b6b", green: "#5be37d", blue: "#6aa8ff" };

function overlay(header) {
  const canvas = $("overlay"); const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  ctx.lineWidth = 2; ctx.font = "12px system-ui, sans-serif";
  Object.entries(header.overlay || {}).forEach(([colour, corners], i) => {
    const hue = CHANNEL_COLOURS[colour] || "#ffd33d";
    ctx.setLineDash([8, 6]); ctx.lineDashOffset = 4 * i; ctx.strokeStyle = hue; ctx.beginPath();
    corners.forEach(([x, y], k) => (k ? ctx.lineTo : ctx.moveTo).call(ctx, x * canvas.width, y * canvas.height));
    ctx.closePath(); ctx.stroke();
    // one label per colour, stacked above the rectangle's corner (registered colours usually nearly coincide)
    ctx.fillStyle = hue; ctx.fillText(colour, corners[0][0] * canvas.width + 4, corners[0][1] * canvas.height - 6 - 14 * i);
  });
  const w = header.zoom_window; const full = header.full_shape || header.shape;
  if (w && full) {
    ctx.setLineDash([]); ctx.strokeStyle = "#4c9bff";
    ctx.strokeRect(w[1] / full[1] * canvas.width, w[0] / full[0] * canvas.height,
      w[3] / full[1] * canvas.width, w[2] / full[0] * canvas.height);
  }
}

function statistics(stats) {
  const pct = (v) => (100 * v).toFixed(v < 0.01 ? 3 : 1) + " %";
  for (let c = 0; c < 3; c++) { $("peak-" + c).textContent = pct(stats.peak[c]); $("mean-" + c).textContent = pct(stats.mean[c]); }
  $("saturated").textContent = pct(stats.saturated) + " of pixels";
  const canvas = $("histogram"); const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const top = Math.log10(1 + Math.max(...stats.histogram.flat()));
  for (let c = 0; c < 3; c++) {
    const bins = stats.histogram[c]; ctx.strokeStyle = COLOURS[c]; ctx.beginPath();
    bins.forEach((n, i) => {
      const x = (i + 0.5) / bins.length * canvas.width;
      const y = canvas.height - 4 - Math.log10(1 + n) / top * (canvas.height - 10);
      (i ? ctx.lineTo : ctx.moveTo).call(ctx, x, y);
    });
    ctx.stroke();
  }
  ctx.fillStyle = "#8b93a1"; ctx.fillText("0", 2, canvas.height - 2); ctx.fillText("full scale", canvas.width - 52, canvas.height - 2);
}

function state(s) {
  $("fps").textContent = s.fps.toFixed(1);
  $("events").textContent = s.events.slice().reverse().join("\n");
  const laser = s.laser || {};
  $("laser-error").textContent = laser.error || "";
  $("unknown").hidden = !laser.unknown; $("unknown").textContent = laser.unknown || "";
  for (const ch of laser.channels || []) {
    laserState[ch.name] = ch;
    const row = $("laser-" + ch.name); if (!row) continue;
    const emit = row.querySelector(".emit");
    emit.textContent = ch.emission ? "ON" : "off"; emit.className = "emit" + (ch.emission ? " emit-on" : "");
    emit.disabled = !laser.connected;
    row.querySelector(".readback").textContent = ch.setpoint_mw === undefined ? "–" :
      `set ${ch.setpoint_mw} mW` + (ch.measured_mw === null ? "" : `\nout ${ch.measured_mw} mW`);
    const interlock = ch.interlock === false ? "INTERLOCK OPEN" : ch.interlock ? "interlock ok" : "";
    row.querySelector(".status").textContent = [interlock, ...(ch.faults || [])].join(", ");
  }
  reconnectable("laser", laser.connected !== false);
  if (s.camera) { $("camera-error").textContent = s.camera.error || ""; reconnectable("camera", s.camera.connected); }
  const job = s.job;
  $("job").textContent = job.busy ? `${job.busy}` + (job.progress ? ` ${job.progress.done}/${job.progress.total}` : "…")
    : job.error ? "error: " + job.error : job.last ? `${job.last} done in ${job.seconds} s` : "";
  $("show").disabled = !!job.busy; $("capture").disabled = !!job.busy;
  if (s.slm) {
    const shows = s.slm.shows;
    const key = `${shows.frame}|${shows.by}|${shows.at}`;
    if (key !== shownFrame) { shownFrame = key; thumbnail(); }
    $("slm-shows").textContent = describe(shows);
    $("slm-error").textContent = s.slm.connected ? "" : s.slm.error || "";
    reconnectable("slm", s.slm.connected);
  }
  for (const [id, name] of Object.entries(s.uploads)) {
    if (![...$("target").options].some((o) => o.value === "upload:" + id)) option($("target"), "upload:" + id, `${name} (upload ${id})`);
  }
  const p = s.procedure;
  $("procedure-lines").textContent = p.lines.join("\n") || $("procedure-lines").textContent;
  $("report").hidden = !p.report;
  $("stop").disabled = !p.running;
}

let thumbnailUrl = null;
async function thumbnail() {
  const response = await fetch("/api/slm/thumbnail.png", { credentials: "omit", headers: { "x-benchctl-token": TOKEN } });
  if (!response.ok) return;
  if (thumbnailUrl) URL.revokeObjectURL(thumbnailUrl);
  thumbnailUrl = URL.createObjectURL(await response.blob());
  $("thumbnail").src = thumbnailUrl;
}

// A device the console lost or could not open: its panel offers to connect it again.
function reconnectable(device, connected) {
  document.querySelector(`.reconnect[data-device="${device}"]`).hidden = !!connected;
}

function when(iso) { return iso ? new Date(iso).toLocaleTimeString() : ""; }

// What the SLM shows: the pattern this console sent, or what the device says it holds and who put it there.
function describe(shows) {
  if (!shows.kind) {
    if (shows.frame === undefined || (shows.frame === null && !shows.by)) return "nothing shown yet";
    return `SLM frame ${shows.frame ?? "?"}, shown by ${shows.by || "a program unknown to the SLM"}` +
      (shows.at ? ` at ${when(shows.at)}` : "") + (shows.channel ? ` for ${shows.channel}` : "") +
      " (read from the SLM)";
  }
  const parts = [shows.kind];
  if (shows.channel) parts.push(`for ${shows.channel}`);
  if (shows.kind === "grating") parts.push(`period ${shows.period_px} px, ${shows.angle_deg}°`);
  if (shows.kind === "flat") parts.push(`${shows.phase_rad} rad`);
  if (shows.kind === "hologram") parts.push(`${shows.target} by ${shows.method}`);
  if (shows.hologram) parts.push(`${shows.hologram.seconds} s${shows.hologram.cached ? " (cached)" : ""}`);
  const z = Object.entries(shows.zernike || {}).filter(([, v]) => v);
  if (z.length) parts.push("+ " + z.map(([k, v]) => `${k} ${v}`).join(", ") + " waves");
  return parts.join(" · ") + ` · SLM frame ${shows.frame}` + (shows.at ? ` at ${when(shows.at)}` : "");
}

function pattern() {
  const kind = $("kind").value;
  const p = { kind, channel: $("channel").value };
  if (kind === "flat") p.phase_rad = Number($("phase_rad").value);
  if (kind === "grating") { p.period_px = Number($("period_px").value); p.angle_deg = Number($("angle_deg").value); }
  if (kind === "hologram") {
    p.target = $("target").value; p.method = $("method").value;
    if ($("iterations").value) p.iterations = Number($("iterations").value);
    if ($("checkpoint").value) p.checkpoint = $("checkpoint").value;
  }
  if (kind !== "blank") {
    p.zernike = {};
    for (const input of $("zernike").querySelectorAll("input")) if (Number(input.value)) p.zernike[input.dataset.term] = Number(input.value);
  }
  return p;
}

$("kind").onchange = showFields;
for (const button of document.querySelectorAll(".reconnect")) {
  button.onclick = () => api("/api/connect", { device: button.dataset.device })
    .then((r) => say(`${button.dataset.device}: ${r.connected ? "connected" : r.error}`), () => {});
}
$("show").onclick = () => api("/api/slm", pattern()).catch(() => {});
// ALL OFF goes over the open socket first: it needs no new connection, so a flood of connections to the console
// cannot hold it up; a request is the fallback when the socket is closed or does not answer within 2 s.
let allOffWait = null;
function allOff() {
  if (socket && socket.readyState === 1) {
    socket.send("all-off");
    clearTimeout(allOffWait);
    allOffWait = setTimeout(allOffByRequest, 2000);
  } else allOffByRequest();
}
function allOffByRequest() { allOffWait = null; api("/api/laser/off", {}).then(() => say("all off"), () => {}); }
function allOffAnswered(answer) {
  clearTimeout(allOffWait); allOffWait = null;
  say(answer.error ? "ALL OFF: " + answer.error : answer.stopped ? "all off: the procedure was stopped" : "all off");
}
$("all-off").onclick = allOff;
$("zoom-clear").onclick = () => api("/api/view", { zoom: null }).catch(() => {});
for (const radio of document.querySelectorAll("input[name=mode]")) radio.onchange = () => api("/api/view", { mode: radio.value }).catch(() => {});
$("frame").onclick = (event) => {
  const box = event.target.getBoundingClientRect();
  api("/api/view", { zoom: [(event.clientX - box.left) / box.width, (event.clientY - box.top) / box.height] }).catch(() => {});
};
$("upload").onchange = async () => {
  const file = $("upload").files[0]; if (!file) return;
  const r = await api("/api/upload?name=" + encodeURIComponent(file.name), await file.arrayBuffer(), true).catch(() => null);
  if (r) { option($("target"), r.target, `${file.name} (${r.target})`); $("target").value = r.target; }
};
$("capture").onclick = () => api("/api/capture", { frames: Number($("frames").value) })
  .then((r) => { $("capture-result").textContent = `${r.folder}: ${r.files.join(", ")}`; }, () => {});
$("dry-run").onclick = () => api("/api/procedures/dry-run", { name: $("procedure").value })
  .then((r) => { $("procedure-lines").textContent = r.lines.join("\n"); $("start").disabled = false; }, () => {});
$("procedure").onchange = () => { $("start").disabled = true; };
$("start").onclick = () => api("/api/procedures/start", { name: $("procedure").value }).then(() => { $("start").disabled = true; }, () => {});
$("stop").onclick = () => api("/api/procedures/stop", {}).catch(() => {});
init();
