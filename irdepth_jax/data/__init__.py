"""Datasets: synthetic LWIR scenes, our folder format, MS2, augmentation and the loader."""
