"""Shapes: the Clevr shape set, and (later) the DeepSDF shape prior."""
