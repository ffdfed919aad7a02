"""File input and output: images, label volumes, meshes. Every write is atomic."""

#: label volume formats (lower-case name endings); here, without numpy, for the command line's help
LABEL_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd", ".npy")

SPACING_RANGE_MM = (1e-7, 1e6)
"""Voxel sizes read as damaged or in other units than mm: a tenth of a nanometre (an atom)
to a kilometre. Beyond them the stages' arithmetic leaves its range (the squared edges of
1e18 mm voxels overflow; 1e-20 mm voxels smoothed 0.4 to 0.75 voxel from the same model's
at 1 mm)."""
