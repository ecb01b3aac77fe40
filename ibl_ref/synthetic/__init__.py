"""Deterministic synthetic environments and meshes with known answers."""
