"""`relight bake --method cuts`: light points, light tree and per-vertex visibility cuts (Cheslack-Postava et al. 2008)."""
