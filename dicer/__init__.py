"""dicer: all-hexahedral finite-element models from CT and MR scans (Canton & Gilchrist's DICER)."""

__version__ = "0.1.0"
