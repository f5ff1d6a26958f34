"""Landmark tracking and head-motion separation."""
