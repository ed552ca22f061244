"""The paper's 2-D object-centric baselines, written from their papers for the same 64x64 Clevr data:
Slot Attention (Locatello et al. 2020) so far; Genesis and MONet to follow (the 2-D baselines issue)."""
