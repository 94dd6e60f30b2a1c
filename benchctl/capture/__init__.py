"""Turning captured RAW frames into measurements: RAW decode (`raw`), DNG writing for the simulated camera
(`dng`), colour merge, registration and scoring. Imports `benchctl.optics` for metrics, nothing from devices."""
