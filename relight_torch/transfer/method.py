"""The 'transfer' method's relight-side registry entry (`relight_torch.methods`)."""

from relight_torch.methods import RelightMethod
from relight_torch.transfer.open import open_transfer_relighter

METHOD = RelightMethod("transfer", open_transfer_relighter, builds_on=("direct",))
