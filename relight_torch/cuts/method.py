"""The 'cuts' method's relight-side registry entry (`relight_torch.methods`)."""

from relight_torch.cuts.open import open_cuts_relighter
from relight_torch.methods import RelightMethod

METHOD = RelightMethod("cuts", open_cuts_relighter, builds_on=("direct",))
