"""Relighting with a moving camera (Kim, Kyung & Lee 2009).

A 'multiview' cache holds the deep framebuffers of several caching cameras. For a new view the
visible points (found by the caller, e.g. Embree primary rays in `pipeline.bake.multiview.view`)
are matched to the caching camera that sees each best (eq. 5, `correspondence`), small holes are
filled from neighbours and larger ones reported (`holes`), and the gathered parameters form an
ordinary GBuffer that the direct `Relighter` shades (`relighter.MultiviewRelighter`).
"""
