"""`relight bake --method cuts` (Cheslack-Postava et al. 2008): light points, light tree, per-vertex visibility cuts."""
