"""Workflows that compose the layers below: holograms for a scene, the hologram cache, the procedure engine
(plan, dry run, execute, resume, run records, reports, calibration store), the built-in procedures (`builtin/`),
the device commands, and the learned methods' checkpoints and training (`learned/`)."""
