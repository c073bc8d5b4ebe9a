"""Lightning's DDP strategy, able to run a stage that has no trainable parameter (the quantizer's closed-form EM)."""

from __future__ import annotations

from lightning.pytorch.strategies import DDPStrategy as LightningDDPStrategy

__all__ = ["DDPStrategy"]


class DDPStrategy(LightningDDPStrategy):
    """``strategy: ddp``, which also runs a module without trainable parameters (unwrapped: nothing to reduce)."""

    def configure_ddp(self) -> None:
        if any(p.requires_grad for p in self.model.parameters()):
            super().configure_ddp()
