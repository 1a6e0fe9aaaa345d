"""spikegen: spike-camera sensor model, spike files and synthetic dataset generation.

Pure NumPy at its core; Blender (`bpy`) is imported only by :mod:`spikegen.render_blender`
and torch never.
"""
__version__ = "0.1.0"
