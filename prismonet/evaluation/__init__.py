"""Evaluation: the measures of the paper's Clevr table, and the ``prismonet evaluate`` command."""
