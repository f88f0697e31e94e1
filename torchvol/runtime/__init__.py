"""Process plumbing: thread counts, the heap, the `compile` setting, progress bars, and the tuning
torchvol applies to its own processes (`runtime.process`)."""
