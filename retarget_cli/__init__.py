"""retarget: performance-driven blendshape retargeting from video (Chuang & Bregler 2002)."""

__version__ = "0.1.0"
