"""The schema's building blocks: strict models and batch roles, registries of techniques, the batch
of scenes seen as one, key paths and the one validation helper."""
