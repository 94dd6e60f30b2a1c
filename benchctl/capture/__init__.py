"""Turning captured RAW frames into measurements: RAW decode and frame averaging (`raw`), camera-SLM registration
(`registration`), SLM lookup-table calibration (`lut_calibration`), registered, balanced, scored colour captures
(`colour_planes`), and a frame at a glance (`preview`). Imports `benchctl.optics` for metrics, nothing from devices,
cgh or the runner. Import from the modules: `raw` and `preview` load no torch (`benchctl camera show` uses them).
"""
