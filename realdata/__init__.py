"""Real photos: loading, undistortion, cropping and resizing with matching intrinsics, and
colour normalisation of the table to the synthetic ground colour."""
