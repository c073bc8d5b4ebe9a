"""Lightning's DDP strategy, able to run a stage that has no trainable parameter.

The quantizer fits its prototypes by a closed-form EM (no optimiser step), and :class:`torch.nn.parallel.
DistributedDataParallel` refuses a module with no parameter that requires a gradient. :class:`DDPStrategy` keeps
everything of Lightning's (process group, launcher, distributed samplers, collectives) and skips only the wrapper
for such a module: there is no gradient to all-reduce, and the stage gathers what it needs itself (the quantizer
all-gathers its crops before the EM). ``ThreeDQCLI`` uses it wherever a config says ``strategy: ddp``.
"""

from __future__ import annotations

from lightning.pytorch.strategies import DDPStrategy as LightningDDPStrategy

__all__ = ["DDPStrategy"]


class DDPStrategy(LightningDDPStrategy):
    """``strategy: ddp``, which also runs a module without trainable parameters (unwrapped: nothing to reduce)."""

    def configure_ddp(self) -> None:
        if any(p.requires_grad for p in self.model.parameters()):
            super().configure_ddp()
        # else: every process holds the same module (same checkpoint, same seed) and no gradient flows
