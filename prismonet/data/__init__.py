"""Data: the CLEVR-style RGB-D scene generator, dataset formats and the loader."""
