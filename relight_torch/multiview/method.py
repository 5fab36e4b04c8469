"""The 'multiview' method's relight-side registry entry (`relight_torch.methods`)."""

from relight_torch.methods import RelightMethod
from relight_torch.multiview.relighter import open_multiview_relighter

METHOD = RelightMethod("multiview", open_multiview_relighter, builds_on=("direct",), needs_view=True)
