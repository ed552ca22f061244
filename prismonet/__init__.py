"""PriSMONet: weakly supervised multi-object 3-D scene decomposition with deep SDF shape priors.

Conventions used everywhere in this package (see README, "Conventions"):

- Camera frame: OpenCV (x right, y down, z forward). Depth is camera z, not ray length.
- World frame: z up, ground plane at z = 0.
- A transform ``T_a_b`` maps points expressed in frame ``b`` into frame ``a``.
- Dimension letters: B batch, K objects (slots), R rays, S samples per ray, H/W image size,
  C channels, D latent size.

Importing this package is cheap: heavy libraries (torch, open3d, cv2) are imported by the
submodules that need them.
"""

__version__ = "0.1.0"
