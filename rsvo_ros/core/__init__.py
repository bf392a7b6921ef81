"""Geometry shared by every layer: SO(3), the rolling-shutter camera, projections (pure numpy)."""
