"""The built-in procedures; each is a module with DESCRIPTION, PARAMETERS and plan() (benchctl.runner.procedure)."""
