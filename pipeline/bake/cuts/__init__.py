"""`relight bake --method cuts`: light points, light tree and per-vertex visibility cuts (seed 004)."""
