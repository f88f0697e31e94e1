"""The scene: its validated model, quality levels, bundled presets and loading."""
