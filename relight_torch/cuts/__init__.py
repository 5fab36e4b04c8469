"""Cheslack-Postava et al. 2008's nonlinear cut approximation: a light tree in post-order (`tree`), sorted sparse cuts
and their selection (`cuts`), the batched cut merge (`merge`), the dome's light per leaf (`env`),
the BRDF per block of merged entries, eager or compiled (`blocks`), the relighter (`relighter`) and
opening a 'cuts' cache (`open`). See docs/CUTS.md."""
