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
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec

from benchctl.calibration_files import check_calibration
from benchctl.errors import BenchctlError
from benchctl.files import file_sha256, write_json
from benchctl.memory import check_memory
from benchctl.profiles import Profile, load_profile, resolve_profile_path
from benchctl.devices.power import format_power
from benchctl.runner.calibration import REGISTRATION_FILE, Calibration
from benchctl.runner.context import Context, Step
from benchctl.runner.instruments import Instruments
from benchctl.runner.layout import CALIBRATION_COPY, DEVICES, PROFILE_COPY, REPORT
from benchctl.runner.procedure import Procedure, load_procedure
from benchctl.runner.record import RunRecord, create_run, open_run


@dataclass
class RunOutcome:
    """What `run_procedure` did: the run folder (None for a dry run), steps run and skipped, the headline."""

    folder: Path | None
    ran: list[str]
    skipped: list[str]
    headline: list[str]


def _line(step: Step) -> str:
    """A step as the dry run and the run print it: its description and every exposure it declares."""
    return step.description + "".join(f"  [{expose.describe()}]" for expose in step.exposes)


def _describe(steps: list[Step], procedure: Procedure, profile: Profile) -> list[str]:
    """The dry run's account: every step with its exposures, then per laser channel the exposures and the highest
    power the plan declares against the channel's limit (exposures whose power is chosen at run time are bounded
    by the limit itself)."""
    lines = [f"procedure {procedure.name!r} ({procedure.kind}) on profile {profile.name!r} ({profile.path}): "
             f"{len(steps)} steps"]
    lines += [f"  {number:>3}. {step.key}: {_line(step)}" for number, step in enumerate(steps, 1)]
    exposures = [expose for step in steps for expose in step.exposes]
    for channel in profile.channels:
        mine = [expose for expose in exposures if expose.channel == channel.name]
        if mine:
            known = [expose.power_w for expose in mine if expose.power_w is not None]
            highest = f"at most {format_power(max(known))}" if known else "powers chosen at run time"
            chosen = sum(expose.power_w is None for expose in mine)
            later = f" ({chosen} at a power chosen at run time)" if known and chosen else ""
            lines.append(f"  {channel.name}: {len(mine)} exposure(s), {highest}{later}; limit "
                         f"{channel.max_power_mw:g} mW")
    return lines


def _resumed(folder: Path, profile_arg: str | None) -> tuple[RunRecord, Procedure, Profile]:
    """Reopen a run: its procedure copy, and the profile it used (which must not have changed)."""
    record = open_run(folder)
    info = record.info()
    for name, digest in info.get("procedure_sha256", {}).items():  # checked before any procedure code runs
        copy = record.folder / name
        if not copy.is_file() or file_sha256(copy) != digest:
            raise BenchctlError(f"{copy} changed since run {record.name} started (or is missing); a resumed run "
                                "runs only the procedure code it started with")
    procedure = load_procedure(record.folder / info["procedure_file"], copies=record.folder)
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
                  dry_run: bool = False, resume: Path | None = None,
                  say: Callable[[str], None] = print) -> RunOutcome:
    """Run (or with `dry_run` only plan and print) a procedure file; `resume` finishes an earlier run instead."""
    if resume is not None:
        record, procedure, bench_profile = _resumed(Path(resume), profile)
        calibration = Calibration(record.folder / CALIBRATION_COPY, bench_profile)
    else:
        if path is None:
            raise BenchctlError("give a procedure file (or --resume RUN_DIR)")
        procedure = load_procedure(path)
        bench_profile = load_profile(profile)
        calibration = Calibration.store(bench_profile)
        record = None
    try:  # every calibration file the run will use, checked before a device opens
        effective = procedure.params.applied_to(calibration.applied(bench_profile))
        checked = check_calibration(effective, calibration.folder / REGISTRATION_FILE)
    except BenchctlError as exc:
        if record is None:
            raise
        raise BenchctlError(f"{exc} (a resumed run uses its own copy of the calibration: repair it, or copy the file "
                            f"from {Calibration.store(bench_profile).folder} over it)") from None
    checked += check_memory(effective, procedure.params, str(path or procedure.name))  # counts that scale memory
    with Instruments(effective, say) as instruments:
        context = Context(effective, procedure.params, calibration, instruments, record, say)
        steps = procedure.plan(context)
        if dry_run:
            for line in [*_describe(steps, procedure, bench_profile), *checked]:
                say(line)
            code = [name for name in procedure.files if name.endswith(".py")]
            say("dry run: nothing was touched" if not code else
                f"dry run: benchctl opened no device and wrote nothing; the procedure's own code ({', '.join(code)}) "
                "ran to plan these steps, with your rights")
            return RunOutcome(None, [], [step.key for step in steps], [])
        if record is None:
            record = create_run(Path(out), procedure.name, {
                "procedure": procedure.kind, "procedure_file": next(iter(procedure.files)),
                "profile": bench_profile.name, "profile_path": str(bench_profile.path.resolve()),
                "parameters": msgspec.to_builtins(procedure.params), "plan": [step.key for step in steps],
                "procedure_sha256": {name: hashlib.sha256(data).hexdigest() for name, data in procedure.files.items()},
            }, {**procedure.files, PROFILE_COPY: bench_profile.path.read_bytes()})
            calibration = Calibration.store(bench_profile).copy_to(record.folder / CALIBRATION_COPY)
            context.calibration, context.record = calibration, record
        say(f"run folder: {record.folder}")
        for reason in [*record.invalidated, *record.damaged]:
            say(reason)
        return _execute(steps, context, record)


def _execute(steps: list[Step], context: Context, record: RunRecord) -> RunOutcome:
    """Run the unfinished steps in order; log each; write the stop record however it ends."""
    ran, skipped = [], []
    current = None
    try:
        for number, step in enumerate(steps, 1):
            if record.is_done(step.key):
                skipped.append(step.key)
                continue
            current = step.key
            context.say(f"[{number}/{len(steps)}] {_line(step)}")
            record.started(step.key)
            start = time.perf_counter()
            context.step = step
            try:
                result = step.action(context)
            except BaseException as exc:
                _best_effort(context, "log the failed step",
                             functools.partial(record.failed, step.key, time.perf_counter() - start, exc))
                raise
            finally:
                context.step = None
            record.finished(step.key, time.perf_counter() - start, result)
            ran.append(step.key)
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
    _save_devices(context, record)
    record.finish("finished", ran=len(ran), skipped=len(skipped))
    headline = list(record.done.get(steps[-1].key, {}).get("headline", [])) if steps else []
    if skipped:
        context.say(f"resumed: {len(skipped)} finished step(s) kept, {len(ran)} run now")
    for line in headline:
        context.say(line)
    context.say(f"record: {record.folder}" + (f"  (report: {record.folder / REPORT})"
                                              if (record.folder / REPORT).is_file() else ""))
    return RunOutcome(record.folder, ran, skipped, headline)


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
