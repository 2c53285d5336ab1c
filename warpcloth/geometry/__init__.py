"""Host-side geometry that needs no Model: rigid transforms and motions, meshes of simple shapes."""
