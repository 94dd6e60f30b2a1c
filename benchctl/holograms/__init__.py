"""Holograms for a calibrated bench: a scene's holograms and scores (`scene`), the cache a run and the console
share (`cache`), `benchctl generate` (`generate`), and the learned methods' checkpoint files and the one search
rule for them (`checkpoints`, `checkpoint_notes`)."""
