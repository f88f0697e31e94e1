"""Process plumbing: thread counts, the heap, torch.compile settings, progress bars, and the tuning
torchvol applies to its own processes (`runtime.process`)."""
