"""Learned methods on disk: checkpoint files (`checkpoint`), training images (`data`), the geometry a network
was trained for (`geometry`) and the training workflow behind `benchctl train` (`training`). The networks and
losses themselves are algorithms and live in `benchctl.cgh.learned`."""
