"""`relight bake --method multiview`: caching cameras placed automatically, and their deep framebuffers.

After Kim, Kyung & Lee 2009: importance-weighted surface samples (`samples`); primary
omni-directional cameras at the centres of maximal empty spheres (`spheres`); secondary cameras
where rays from still-uncovered samples meet in a voting grid (`voting`); camera attributes from
the samples each covers (`cameras`, `placement`); a deep framebuffer per caching camera through the
existing baker, recorded in one cache layer (`bake`). For relighting, `view` traces a new camera's
primary rays and `holes` bakes the surfaces no caching camera saw, on demand.
"""
