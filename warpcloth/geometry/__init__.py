"""Host-side geometry that needs no Model: rigid transforms and the meshes of simple shapes."""
