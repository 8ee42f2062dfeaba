"""Shipped rig data (the embedded default rig)."""
