"""`benchctl run`: plan a procedure, then run its steps into a new run folder (or finish an interrupted one).

The plan is made before anything is touched, so `--dry-run` prints exactly the steps a run would take. A run
logs each step as it starts and finishes; on any exit (error, Ctrl-C, SIGTERM) the instruments close with every
laser channel off and the run's stop record says where it stopped (the first error is the one reported, even
when a full disk stops the record-keeping too). `--resume` checks the run's own copy of the procedure against
the hashes taken at its start before any of it runs, reloads it and the calibration, checks the profile is
unchanged, and runs only the steps not finished (or whose captured files changed).
"""

from __future__ import annotations

import functools
import hashlib
import json
import time
from collections import Counter
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec

from benchctl.calibration.acceptance import rejection_line
from benchctl.calibration.calibrated import Calibrated
from benchctl.calibration.files import check_calibration
from benchctl.calibration.store import FOCUS_FILE, REGISTRATION_FILE, Calibration
from benchctl.devices.power import format_power
from benchctl.errors import BenchctlError
from benchctl.files import file_sha256, folder_problem, write_json
from benchctl.memory import check_memory, peak_lines
from benchctl.profiles import Profile, load_profile, resolve_profile_path
from benchctl.runner.context import Context, Expose, FocusAt, Step, StepRedo
from benchctl.runner.estimates import RunEstimate, duration_text
from benchctl.runner.instruments import Instruments
from benchctl.runner.layout import CALIBRATION_COPY, DEVICES, PROFILE_COPY, REPORT, RUN_FILE
from benchctl.runner.procedure import Procedure, load_procedure
from benchctl.schema import fail
from benchctl.runner.record import RunRecord, create_run, open_run, run_folder_lock, set_aside


@dataclass
class RunOutcome:
    """What `run_procedure` did: the run folder (None for a dry run), steps run and skipped, the headline."""

    folder: Path | None
    ran: list[str]
    skipped: list[str]
    headline: list[str]


def _line(step: Step) -> str:
    """A step as the dry run and the run print it: its description, every focus move and exposure it declares."""
    declared: list[FocusAt | Expose] = [*step.focus, *step.exposes]
    return step.description + "".join(f"  [{item.describe()}]" for item in declared)


def _describe(steps: list[Step], procedure: Procedure, profile: Profile) -> list[str]:
    """The dry run's account: every step with its exposures, then per laser channel the exposures and the highest
    power the run may reach against the channel's limit: the powers the plan declares, and for those chosen at run
    time (automatic exposure) the bound they are chosen under (the procedure's cap, else the channel's limit)."""
    lines = [f"procedure {procedure.name!r} ({procedure.kind}) on profile {profile.name!r} ({profile.path}): "
             f"{len(steps)} steps"]
    lines += [f"  {number:>3}. {step.key}: {_line(step)}" for number, step in enumerate(steps, 1)]
    exposures = [expose for step in steps for expose in step.exposes]
    for channel in profile.channels:
        mine = [expose for expose in exposures if expose.channel == channel.name]
        if mine:
            known = [expose.power_w for expose in mine if expose.power_w is not None]
            bounds = [expose.max_w if expose.max_w is not None else channel.max_power_mw * 1e-3
                      for expose in mine if expose.power_w is None]
            later = (f" ({len(bounds)} at a power chosen at run time, up to {format_power(max(bounds))}"
                     + (", the channel's limit" if max(bounds) >= channel.max_power_mw * 1e-3 else "")
                     + ")" if bounds else "")
            lines.append(f"  {channel.name}: {len(mine)} exposure(s), at most {format_power(max(known + bounds))}"
                         f"{later}; limit {channel.max_power_mw:g} mW")
    return lines


def _resumed(folder: Path, profile_arg: str | None, allow_code: bool) -> tuple[RunRecord, Procedure, Profile]:
    """Reopen a run: its procedure copy, and the profile it used (which must not have changed)."""
    record = open_run(folder)
    info = record.info()
    for key in ("procedure_file", "profile_path"):
        if info.get(key) is None:
            raise fail(folder / RUN_FILE, key, "missing required key")
    for name, digest in info.get("procedure_sha256", {}).items():  # checked before any procedure code runs
        copy = record.folder / name
        if not copy.is_file() or file_sha256(copy) != digest:
            raise BenchctlError(f"{copy} changed since run {record.name} started (or is missing); a resumed run "
                                "runs only the procedure code it started with")
    procedure = load_procedure(record.folder / info["procedure_file"], copies=record.folder, allow_code=allow_code)
    source = Path(info["profile_path"])
    if profile_arg is not None and resolve_profile_path(profile_arg).resolve() != source.resolve():
        raise BenchctlError(f"{folder}: this run used profile {source}; resume it with that profile (or none)")
    try:
        unchanged = source.read_bytes() == (record.folder / PROFILE_COPY).read_bytes()
    except OSError as exc:
        raise BenchctlError(f"{folder}: cannot read the run's profile {source}: {exc.strerror or exc}") from None
    if not unchanged:
        raise BenchctlError(f"{source} changed since run {record.name} started; a resumed run must use the profile "
                            f"it started with (the original is kept as {record.folder / PROFILE_COPY})")
    return record, procedure, load_profile(source)


def run_procedure(path: Path | None, *, profile: str | None = None, out: Path = Path("runs"),
                  dry_run: bool = False, resume: Path | None = None, allow_code: bool = False,
                  say: Callable[[str], None] = print,
                  events: Callable[[dict[str, Any]], None] | None = None) -> RunOutcome:
    """Run (or with `dry_run` only plan and print) a procedure file; `resume` finishes an earlier run instead. The run
    folder is locked (`run_folder_lock`) for as long as this writes it. `allow_code`: Python code that a TOML
    procedure names, or that a resumed run kept, may run (load_procedure). `events`: told the run's events as they
    happen (`runner.events` says which), for a program that follows the run."""
    with ExitStack() as held:
        return _run(path, profile, out, dry_run, resume, allow_code, say, events, held)


def _run(path: Path | None, profile: str | None, out: Path, dry_run: bool, resume: Path | None, allow_code: bool,
         say: Callable[[str], None], events: Callable[[dict[str, Any]], None] | None,
         held: ExitStack) -> RunOutcome:
    if resume is not None:
        if not (Path(resume) / RUN_FILE).is_file():
            raise BenchctlError(f"{resume}: not a benchctl run folder (no {RUN_FILE})")
        held.enter_context(run_folder_lock(Path(resume)))
        record, procedure, bench_profile = _resumed(Path(resume), profile, allow_code)
        calibration = Calibration(record.folder / CALIBRATION_COPY, bench_profile)
        changed = record.changed_calibration(calibration.folder)
        if changed:
            raise BenchctlError(f"{calibration.folder}/{changed}: a resumed run uses the calibration its finished "
                                "steps were computed with; put that file back, or start a new run")
        calibration = _usable_calibration(record, calibration, procedure, bench_profile, dry_run, say)
    else:
        if path is None:
            raise BenchctlError("give a procedure file (or --resume RUN_DIR)")
        procedure = load_procedure(path, allow_code=allow_code)
        bench_profile = load_profile(profile)
        calibration = Calibration.store(bench_profile)
        record = None
    bench, checked = _checked_calibration(calibration, procedure, bench_profile)
    effective = bench.profile
    estimates = check_memory(effective, procedure.params, str(path or procedure.name))  # counts that scale memory
    with Instruments(effective, say) as instruments:
        context = Context(bench, procedure.params, instruments, record, say)
        try:
            steps = procedure.plan(context)
        except BenchctlError as exc:  # a value of the procedure's: name its file too
            if not str(exc).startswith("parameters."):
                raise
            where = path if record is None else record.folder / record.info()["procedure_file"]
            raise BenchctlError(f"{where}: {exc}") from None
        checked += peak_lines([*estimates, *(step.memory for step in steps if step.memory is not None)])
        estimate = RunEstimate(steps, effective)
        problem = folder_problem(Path(out)) if record is None else None
        if problem:
            raise BenchctlError(f"--out {out}: {problem}: a run folder cannot be created there")
        todo = [step for step in steps if record is None or not record.is_done(step.key)]
        if dry_run:
            for line in [*_describe(steps, procedure, bench_profile), *checked,
                         *estimate.describe(steps, Path(out))]:
                say(line)
            code = [name for name in procedure.files if name.endswith(".py")]
            say("dry run: nothing was touched" if not code else
                f"dry run: benchctl opened no device and wrote nothing; the procedure's own code ({', '.join(code)}) "
                "ran to plan these steps, with your rights")
            return RunOutcome(None, [], [step.key for step in steps], [])
        estimate.check_disk(todo, record.folder if record is not None else Path(out))
        if record is None:
            record = create_run(Path(out), procedure.name, {
                "procedure": procedure.kind, "procedure_file": next(iter(procedure.files)),
                "profile": bench_profile.name, "profile_path": str(bench_profile.path.resolve()),
                "parameters": msgspec.to_builtins(procedure.params), "plan": [step.key for step in steps],
                "procedure_sha256": {name: hashlib.sha256(data).hexdigest() for name, data in procedure.files.items()},
            }, {**procedure.files, PROFILE_COPY: bench_profile.path.read_bytes()})
            held.enter_context(run_folder_lock(record.folder))
            calibration = Calibration.store(bench_profile).copy_to(record.folder / CALIBRATION_COPY)
            record.calibration_written(calibration.checksums())
            context.bench, context.record = Calibrated(bench.configured, calibration), record
        say(f"run folder: {record.folder}")
        if events is not None:
            record.listener = events
            events({"event": "run", "folder": str(record.folder.resolve()), "steps": len(steps), "todo": len(todo),
                    "resumed": resume is not None})
        for reason in [*record.invalidated, *record.damaged]:
            say(reason)
        return _execute(steps, context, record, estimate)


def _checked_calibration(calibration: Calibration, procedure: Procedure,
                         profile: Profile) -> tuple[Calibrated, list[str]]:
    """The bench as `calibration` calibrates it for `procedure`, and one line per calibration file checked: every file
    the run will use, checked before a device opens (a bad one is a BenchctlError naming it)."""
    bench = Calibrated(procedure.params.applied_to(profile), calibration)
    folder = calibration.folder
    return bench, check_calibration(bench.profile, folder / REGISTRATION_FILE, folder / FOCUS_FILE)


def _usable_calibration(record: RunRecord, calibration: Calibration, procedure: Procedure, profile: Profile,
                        dry_run: bool, say: Callable[[str], None]) -> Calibration:
    """The calibration a resumed run goes on with: its own copy, or, where a file of the copy fails its check (a run
    started with a file that older benchctl let through), the store's once it is fixed there: the copy is set aside
    (kept), the store's copied in its place, and every finished step done again (each may have used the bad file)."""
    try:
        _checked_calibration(calibration, procedure, profile)
        return calibration
    except BenchctlError as bad:
        problem = str(bad)
    store = Calibration.store(profile)
    try:
        _checked_calibration(store, procedure, profile)
    except BenchctlError as exc:
        raise BenchctlError(f"{problem}; the store it came from fails too ({exc}): fix the file in {store.folder}, "
                            "and a resume takes the calibration from there") from None
    finished = list(record.done)
    if dry_run:
        say(f"{problem}: a resume would take the fixed calibration from {store.folder} and do its {len(finished)} "
            "finished step(s) again")
        return store
    aside = set_aside(calibration.folder)
    copy = store.copy_to(calibration.folder)
    if finished:
        record.invalidate(finished[0], f"the run's calibration was replaced: {problem}")
    record.calibration_written(copy.checksums(), replace=True)
    say(f"{problem}: this run's copy is kept as {aside}; the run goes on with the fixed calibration from "
        f"{store.folder} and does its {len(finished)} finished step(s) again")
    return copy


MAX_REDOS = 2  # times one run invocation goes back to the same step (StepRedo) before it stops


def _execute(steps: list[Step], context: Context, record: RunRecord, estimate: RunEstimate) -> RunOutcome:
    """Run the unfinished steps in order; log each; write the stop record however it ends. A step that sends the
    run back to an earlier one (StepRedo) has that one and every step finished after it done again."""
    earlier = [step.key for step in steps if record.is_done(step.key)]
    ran: list[str] = []
    redone: Counter[str] = Counter()
    current = None
    try:
        while True:
            todo = [(number, step) for number, step in enumerate(steps, 1) if not record.is_done(step.key)]
            estimate.start([step for _, step in todo])
            try:
                for number, step in todo:
                    current = step.key
                    _run_step(f"[{number}/{len(steps)}, about {duration_text(estimate.left())} left]", step, context,
                              record, estimate)
                    ran.append(step.key)
                break
            except StepRedo as exc:
                if exc.stop or redone[exc.redo] >= MAX_REDOS:
                    raise
                redone[exc.redo] += 1
                context.say(f"      {exc}: step {exc.redo!r} is done again")
        current = None
    except BaseException as exc:
        status = "interrupted" if isinstance(exc, KeyboardInterrupt) else "failed"
        _best_effort(context, "save devices.json", lambda: _save_devices(context, record))
        _best_effort(context, "write the stop record",
                     functools.partial(record.finish, status, step=current, error=f"{type(exc).__name__}: {exc}"))
        context.say(f"run {status} at step {current!r}; everything captured so far is in {record.folder}; "
                    f"finish it with: benchctl run --resume {record.folder}")
        if isinstance(exc, OSError):  # the disk or a device file failed: one line, not a traceback
            raise BenchctlError(f"step {current!r}: {exc}") from exc
        raise
    skipped = [key for key in earlier if key not in ran]
    ran = list(dict.fromkeys(ran))
    _save_devices(context, record)
    rejected = [rejection_line(result["calibration"]) for result in record.done.values()
                if isinstance(result.get("calibration"), dict) and not result["calibration"]["stored"]]
    record.finish("finished", ran=len(ran), skipped=len(skipped), **({"not_stored": rejected} if rejected else {}))
    headline = list(record.done.get(steps[-1].key, {}).get("headline", [])) if steps else []
    if skipped:
        context.say(f"resumed: {len(skipped)} finished step(s) kept, {len(ran)} run now")
    for line in headline:
        context.say(line)
    context.say(f"record: {record.folder}" + (f"  (report: {record.folder / REPORT})"
                                              if (record.folder / REPORT).is_file() else ""))
    if rejected:
        raise BenchctlError("; ".join(rejected) + f" (report: {record.folder / REPORT}; accept = \"always\" in the "
                            "procedure's [parameters] stores a calibration that fails its acceptance test)")
    return RunOutcome(record.folder, ran, skipped, headline)


def _run_step(where: str, step: Step, context: Context, record: RunRecord, estimate: RunEstimate) -> None:
    """Run one step and log it: started, then finished with its result, or failed (a StepRedo also marks the step
    it goes back to, and every step finished after that, to be done again). `where` leads its line: [n/N, time
    left]."""
    context.say(f"{where} {_line(step)}")
    record.started(step.key)
    start = time.perf_counter()
    context.step = step
    context.written = {"checksums": {}, "archived": {}}
    try:
        result = step.action(context)
        for kind, files in context.written.items():  # the files the step wrote, with the ones it recorded itself
            if files:
                result = {**result, kind: {**result.get(kind, {}), **files}}
    except StepRedo as exc:
        _best_effort(context, "log the failed step", functools.partial(
            record.failed, step.key, time.perf_counter() - start, exc, exc.redo, exc.diverged))
        record.invalidate(exc.redo, str(exc))
        raise
    except BaseException as exc:
        _best_effort(context, "log the failed step",
                     functools.partial(record.failed, step.key, time.perf_counter() - start, exc))
        raise
    finally:
        context.step = None
    seconds = time.perf_counter() - start
    record.finished(step.key, seconds, result)
    estimate.ran(step, seconds)


def _best_effort(context: Context, what: str, action: Callable[[], object]) -> None:
    """Record-keeping after a failure (a full disk makes it fail too): a failure here is said, and the first
    error stays the one raised."""
    try:
        action()
    except Exception as exc:
        context.say(f"(could not {what}: {exc}; what stopped the run is the error reported with it)")


def _save_devices(context: Context, record: RunRecord) -> None:
    """The devices file: identities of every device opened, in this and earlier attempts of the run."""
    path = record.folder / DEVICES
    known: dict[str, Any] = {}
    if path.is_file():
        known = json.loads(path.read_text())
    write_json(path, {**known, **context.instruments.identities})
