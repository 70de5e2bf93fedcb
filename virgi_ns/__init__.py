"""virgi-ns: VIRGi (view-dependent instant recoloring of 3D Gaussian splats) for nerfstudio."""

__version__ = "0.1.0"
