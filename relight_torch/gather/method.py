"""The 'gather' method's relight-side registry entry (`relight_torch.methods`)."""

from relight_torch.gather.open import open_gather_relighter
from relight_torch.methods import RelightMethod

METHOD = RelightMethod("gather", open_gather_relighter, builds_on=("direct",))
