"""The mesh data model shared by every stage, and the stages that build and change meshes."""

from dicer.mesh.model import Mesh

__all__ = ["Mesh"]
