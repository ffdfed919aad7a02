"""File input and output: images, label volumes, meshes. Every write is atomic."""

#: label volume formats (lower-case name endings); here, without numpy, for the command line's help
LABEL_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd", ".npy")
