"""Utilities every layer may use: the allocator, Ctrl-C, folder locks, files, progress, shape checks."""
