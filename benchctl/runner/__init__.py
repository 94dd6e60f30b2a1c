"""Workflows that compose optics, holograms and (later) devices: generation now, procedures next."""
