"""Cheslack-Postava et al. 2008's nonlinear cut approximation: a light tree in post-order (`tree`), sorted sparse cuts
and their selection (`cuts`), the batched cut merge (`merge`), the dome's light per leaf (`env`),
the merged visibility cuts kept in batches (`batches`), the illumination cut's node tables and
grids (`node_table`), the BRDF factor sums per node (`factors`) per block of merged entries, eager
or compiled (`blocks`), the factor columns kept between frames (`columns`), the relighter
(`relighter`) and opening a 'cuts' cache (`open`). See docs/CUTS.md."""
