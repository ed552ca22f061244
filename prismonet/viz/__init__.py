"""Figures: contact sheets and colour maps (numpy + OpenCV, no plotting library needed)."""
