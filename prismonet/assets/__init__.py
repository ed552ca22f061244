"""Files that ship with the package: the pre-trained Clevr shape prior (and later checkpoints)."""
