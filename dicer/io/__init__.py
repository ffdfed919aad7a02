"""File input and output: images, label volumes, meshes. Every write is atomic."""
