"""Device drivers (laser, SLM, camera) and their simulators; chosen by name in the hardware profile."""
