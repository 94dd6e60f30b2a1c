"""The procedure engine behind one front door (`api`): plan, dry run, execute, resume, run records and reports,
the device commands, and the built-in procedures (`builtin/`)."""
