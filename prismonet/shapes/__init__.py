"""Shapes: the Clevr shape set (``clevr_set``, ``normalize``, ``sdf_samples``) and the frozen DeepSDF
shape prior Φ learnt from it (``decoder``, ``pretrain``, ``prior``), with its measures
(``metrics``, ``evaluate``) and mesh extraction (``mesh``)."""
