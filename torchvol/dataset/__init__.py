"""Datasets: recipes and their distributions, mixed recipes, views, sequences, labels, the file
codec, torch Datasets and the generator."""

from . import mix  # noqa: F401  registers the mixed-recipe form ([[families]]) with Recipe.load
