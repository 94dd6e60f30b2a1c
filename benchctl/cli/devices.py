"""`benchctl laser | slm | camera | focus | sim | devices`: each action maps to one function of
`benchctl.runner.device_commands` (focus: `benchctl.runner.focus_commands`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from benchctl.cli.args import add_profile, positive_int, print_lines


def _cmd_device(args: argparse.Namespace) -> int:
    """laser / slm / sim subcommands: each maps to one function of benchctl.runner.device_commands."""
    from benchctl.profiles import load_profile
    from benchctl.runner import device_commands as dc

    if args.command == "devices":
        return print_lines(dc.devices_found())
    if args.command == "sim":
        if args.sim_command == "status":
            return print_lines(dc.sim_status())
        if args.sim_command == "reset":
            return print_lines(dc.sim_reset())
        return print_lines(dc.sim_fault(args.device, args.faults, args.clear, load_profile(args.profile)))
    if args.command == "camera" and args.camera_command == "show":  # a file: no profile, no camera
        from benchctl.capture.preview import show_frame

        return print_lines(show_frame(Path(args.frame), args.output))
    profile = load_profile(args.profile)
    if args.command == "focus":
        from benchctl.runner import focus_commands as fc

        if args.focus_command == "status":
            return print_lines(fc.focus_status(profile))
        if args.focus_command == "home":
            return print_lines(fc.focus_home(profile))
        if args.focus_command == "move":
            return print_lines(fc.focus_move(profile, args.steps))
        return print_lines(fc.focus_go(profile, " ".join(args.depth), args.channel))
    if args.command == "camera":
        if args.camera_command == "info":
            return print_lines(dc.camera_info(profile))
        return print_lines(dc.camera_capture(profile, Path(args.output), args.frames))
    action = args.laser_command if args.command == "laser" else args.slm_command
    if args.command == "laser":
        if action == "status":
            return print_lines(dc.laser_status(profile))
        if action == "set":
            return print_lines(dc.laser_set(profile, args.channel, " ".join(args.power)))
        if action == "on":
            duration = dc.parse_duration(args.duration) if args.duration else None
            return print_lines(dc.laser_on(profile, args.channel, duration, args.leave_on))
        return print_lines(dc.laser_off(profile, args.channel))
    if action == "info":
        return print_lines(dc.slm_info(profile))
    if action == "show":
        return print_lines(dc.slm_show(profile, Path(args.file), args.channel))
    return print_lines(dc.slm_blank(profile))


def add_commands(sub: argparse._SubParsersAction) -> None:
    """Add this group's sub-commands to the `benchctl` sub-parsers (importing nothing heavy)."""
    laser = sub.add_parser("laser", help="laser: status, setpoints, emission",
                           description="Connecting to the laser turns emission off on every channel (safety); "
                                       "emission is off again when a command exits unless --leave-on says "
                                       "otherwise.").add_subparsers(dest="laser_command", metavar="ACTION",
                                                                    required=True)
    status = laser.add_parser("status", help="per channel: wavelength, setpoint, measured power, emission, "
                                             "interlock, faults (changes nothing)")
    setp = laser.add_parser("set", help="change a channel's power setpoint (emission stays off)")
    setp.add_argument("channel", help="channel name from the profile, e.g. red")
    setp.add_argument("power", nargs="+", help="power: 20mW, 20 mW, 0.02W or 5%% (of the channel's max_power_mw)")
    on = laser.add_parser("on", help="emission on for a time or until Ctrl-C, then off")
    on.add_argument("channel", help="channel name from the profile, e.g. red")
    on.add_argument("--for", dest="duration", metavar="TIME", help="how long, e.g. 30s, 500ms, 2m "
                                                                   "(default: until Ctrl-C)")
    on.add_argument("--leave-on", action="store_true", help="leave emission on after the command exits")
    off = laser.add_parser("off", help="emission off on one channel or all")
    off.add_argument("channel", nargs="?", default="all", help="channel name or 'all' (default: all)")
    for parser in (status, setp, on, off):
        add_profile(parser)
        parser.set_defaults(func=_cmd_device)

    slm = sub.add_parser("slm", help="SLM: info, show an image or phase, blank",
                         description="The phase SLM the profile describes. A phase (.npy, radians) is shown "
                                     "through the channel's lookup table (measured ones from calibration/<profile>/, "
                                     "else linear), with the profile's offset, carrier and flips; an image's gray "
                                     "levels are shown exactly as they are.").add_subparsers(
        dest="slm_command", metavar="ACTION", required=True)
    info = slm.add_parser("info", help="driver, resolution, pitch, bit depth, settle time, lookup tables")
    show = slm.add_parser("show", help="show an 8-bit image as is, or a .npy phase (radians) encoded for a channel")
    show.add_argument("file", help="PNG/TIFF gray image of the SLM's size, or .npy phase in radians")
    show.add_argument("--channel", "-c", help="laser channel whose lookup table encodes a .npy phase")
    blank = slm.add_parser("blank", help="show gray level 0 everywhere")
    for parser in (info, show, blank):
        add_profile(parser)
        parser.set_defaults(func=_cmd_device)

    camera = sub.add_parser("camera", help="camera: info, capture RAW frames, show one",
                            description="The camera the profile describes. Captured RAW files are written the moment "
                                        "they arrive and never modified; `camera show` reads one back (no camera "
                                        "needed).").add_subparsers(
        dest="camera_command", metavar="ACTION", required=True)
    cinfo = camera.add_parser("info", help="what the camera says it is, and the capture settings")
    capture = camera.add_parser("capture", help="capture RAW frames exactly as the camera delivers them")
    capture.add_argument("--output", "-o", required=True, metavar="FILE",
                         help="RAW file to write (several frames: FILE-000.dng, FILE-001.dng, ...)")
    capture.add_argument("--frames", "-n", type=positive_int, help="frames to capture (default: the profile's)")
    for parser in (cinfo, capture):
        add_profile(parser)
        parser.set_defaults(func=_cmd_device)
    show = camera.add_parser("show", help="a RAW frame's size, levels, peak and saturation per colour, and a preview "
                                          "PNG")
    show.add_argument("frame", help="RAW file (DNG, CR2, ... as captured)")
    show.add_argument("--output", "-o", type=Path, metavar="PNG",
                      help="where to write the preview (default: FRAME's name + .preview.png, in this folder)")
    show.set_defaults(func=_cmd_device)
    focus = sub.add_parser("focus", help="camera focus: status, home, move by steps, go to a depth",
                           description="The camera's focus the profile's [focus] section describes (a Zaber stage "
                                       "carrying the camera, or the EOS body's own lens). Steps are the driver's own "
                                       "(microsteps, DriveLens steps); `go` turns a depth into steps with the focus "
                                       "calibration (procedures/focus_calibration.toml) and arrives from its side, "
                                       "past the backlash.").add_subparsers(
        dest="focus_command", metavar="ACTION", required=True)
    fstatus = focus.add_parser("status", help="what the device is, where the focus is (steps, and depth where "
                                              "calibrated)")
    fhome = focus.add_parser("home", help="drive to the home end stop: position 0 from then on")
    fmove = focus.add_parser("move", help="move by STEPS (signed) from where it is")
    fmove.add_argument("steps", type=int, metavar="STEPS", help="steps to move, e.g. 200 or -50")
    fgo = focus.add_parser("go", help="focus at a depth from the SLM: 70.2mm or 14.3D (diopters: 1 / metres)",
                           description="Focus at a depth from the SLM, in millimetres (70.2mm) or diopters (14.3D = "
                                       "1 / 0.0702 m), through the colour's focus calibration: the position is "
                                       "approached from the side it was calibrated from, going past it by twice the "
                                       "measured backlash first when it has to come back. Homes first when the "
                                       "position is not known.")
    fgo.add_argument("depth", nargs="+", metavar="DEPTH", help="e.g. 70.2mm, 70.2 mm, 14.3D")
    fgo.add_argument("--channel", "-c", help="laser colour whose calibration to use (default: green, or the only one)")
    for parser in (fstatus, fhome, fmove, fgo):
        add_profile(parser)
        parser.set_defaults(func=_cmd_device)

    devices = sub.add_parser("devices", help="serial ports, PTP and GenICam cameras, framebuffers and desktop outputs "
                                                     "(EDID name, serial, mode) on this machine")
    devices.set_defaults(func=_cmd_device)

    sim = sub.add_parser("sim", help="the simulated bench's remembered state").add_subparsers(
        dest="sim_command", metavar="ACTION", required=True)
    sim.add_parser("status", help="where the state is kept and what each simulated device holds")
    sim.add_parser("reset", help="forget all simulated device state (like a power cycle)")
    fault = sim.add_parser("fault", help="make a simulated device misbehave from its next connection on")
    fault.add_argument("device", help="simulated device name, e.g. rgb-laser (from sim://rgb-laser), focus-stage, or "
                                      "sim-camera")
    fault.add_argument("faults", nargs="*", help="lasers: no_reply, garbled, echo, slow, interlock_open, device_fault, "
                                                 "clamp, drop_after=N; focus stage: no_reply, garbled, slow, stall, "
                                                 "drop_after=N; sim-camera: unplug_at=N (cable pulled before frame N)")
    fault.add_argument("--clear", action="store_true", help="remove every fault")
    add_profile(fault)  # whose sim:// lasers are known devices
    for parser in sim.choices.values():
        parser.set_defaults(func=_cmd_device)
