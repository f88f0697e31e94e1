"""Datasets: recipes and their distributions, mixed recipes, views, sequences, labels, the file
codec, torch Datasets and the generator."""
