"""The 'direct' method's relight-side registry entry (`relight_torch.methods`)."""

from relight_torch.direct.relighter import open_relighter
from relight_torch.methods import RelightMethod

METHOD = RelightMethod("direct", open_relighter)
