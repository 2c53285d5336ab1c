"""Host-side geometry that needs no Model: rigid transforms, keyframed rigid motions and the meshes of
simple shapes."""
