"""Data shipped with the package: the measured fabrics (materials.json)."""
