"""Localization on top of the kernels: metric localization (translation search + yaw)."""
