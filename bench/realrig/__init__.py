"""Helpers of ``bench/real_rig.py`` (real footage onto the ICT rig against an independent detector).

A package rather than loose ``bench/*.py`` files, so that ``make bench`` (which runs every
``bench/*.py``) does not run them and the unit tests can import :mod:`.measures`.
"""
