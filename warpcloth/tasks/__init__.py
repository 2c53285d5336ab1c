"""Applications written against the public API: the seed's inverse problems (material estimation, the throw into
a basket) and the optimisers they use."""
