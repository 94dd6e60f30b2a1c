"""Training the learned methods (`benchctl train`, also under torchrun): the loop (`training`), its images
(`data`), its health checks (`health`) and weight averaging (`averaging`). The networks and losses themselves are
algorithms and live in `benchctl.cgh.learned`; checkpoint files in `benchctl.holograms.checkpoints`."""
