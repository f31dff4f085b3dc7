"""Adversarial term (Sun et al. 2018: an LSGAN on the pixel module): the term owns its critic and the critic's optimiser.

The LightningModule keeps one optimiser for the network. A term with ``update_critic(out, batch) -> {name: value}``
is called once per training step *before* the losses are computed; it trains the critic on detached predictions,
so the generator term of the same step is computed against the updated critic (their code alternates the two
updates step by step: the same 1:1 ratio). The critic and its optimiser state are this module's ``state_dict``
(``_extra_state`` holds the optimiser), so checkpoints carry them and a resumed run continues the same game.
"""

from __future__ import annotations

from contextlib import contextmanager

import torch
import torch.nn as nn

from nvs.core.types import RGB_BRANCHES, Batch, Outputs, to_model_range
from nvs.core.weight_init import xavier_convs
from nvs.losses.terms import LossTerm, up


class PatchDiscriminator(nn.Module):
    """Sun et al.'s discriminator: (n_layers - 1) 4x4 stride-2 convs (32, 64, 128, 256, 384, 512 channels) with
    LeakyReLU(0.2), no norm, then a 1x1 conv to one logit per patch; Xavier-uniform weights, zero biases.

    (B,3,S,S) in [-1,1] -> logits (B,1,S/2^(n_layers-1),S/2^(n_layers-1)).
    """

    CHANNELS = (32, 64, 128, 256, 384, 512, 512)

    def __init__(self, n_layers: int = 5):
        super().__init__()
        if not 2 <= n_layers <= len(self.CHANNELS) + 1:
            raise ValueError(f"n_layers={n_layers}: expected 2..{len(self.CHANNELS) + 1}")
        chans = self.CHANNELS[:n_layers - 1]
        layers = []
        for cin, cout in zip((3,) + chans[:-1], chans):
            layers += [nn.Conv2d(cin, cout, 4, stride=2, padding=1), nn.LeakyReLU(0.2)]
        self.body = nn.Sequential(*layers, nn.Conv2d(chans[-1], 1, 1))
        xavier_convs(self)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.body(x)


@contextmanager
def frozen(module: nn.Module):
    """The module's parameters take no gradient inside the block (inputs still do)."""
    flags = [p.requires_grad for p in module.parameters()]
    for p in module.parameters():
        p.requires_grad_(False)
    try:
        yield module
    finally:
        for p, flag in zip(module.parameters(), flags):
            p.requires_grad_(flag)


class AdversarialLoss(LossTerm):
    """Least-squares GAN generator term mean (D(I~) - 1)^2 on one prediction, images on [-1,1].

    ``branch``: which prediction the critic judges: a key of ``outputs["rgb_branches"]`` (Sun et al.: ``pixel``, the
    pixel module's output) or null for the final ``rgb``. The critic's loss is mean (D(I_t) - 1)^2 + mean D(I~)^2
    (their ``gan_type: ls``), trained by its own Adam (their ``learning_rate_d`` 1e-4, beta1 0.5). Before
    ``start_step`` critic updates the critic is not trained and the generator term is multiplied by 0 (their
    ``gan_start_step``; 0 = from the first step).
    """

    def __init__(self, weight: float = 1.0, branch: str | None = "pixel", n_layers: int = 5, lr: float = 1e-4,
                 betas=(0.5, 0.999), start_step: int = 0):
        super().__init__(weight)
        if start_step < 0:
            raise ValueError(f"start_step must be >= 0, got {start_step}")
        self.branch = branch
        self.needs = frozenset({RGB_BRANCHES}) if branch is not None else frozenset()
        self._judged = self._final if branch is None else self._branch  # chosen once, not per step
        self.critic = PatchDiscriminator(n_layers)
        self.lr, self.betas, self.start_step = float(lr), tuple(float(b) for b in betas), int(start_step)
        self.register_buffer("steps", torch.zeros((), dtype=torch.long))
        self._optimizer: torch.optim.Optimizer | None = None
        self._pending_state: dict | None = None

    # -- what the critic judges ------------------------------------------------------------------------------------
    def prediction(self, out: Outputs) -> torch.Tensor:
        """The judged prediction on [-1,1]: (B,3,H,W)."""
        return to_model_range(self._judged(out))

    def _final(self, out: Outputs) -> torch.Tensor:
        return out["rgb"]

    def _branch(self, out: Outputs) -> torch.Tensor:
        return out[RGB_BRANCHES][self.branch]

    @property
    def active(self) -> bool:
        # Counted in critic updates: the generator term starts with the critic's first update.
        return self.start_step == 0 or int(self.steps) > self.start_step

    def forward(self, out: Outputs, batch: Batch) -> torch.Tensor:
        fake = self.prediction(out)
        # The generator's gradient flows through the critic into the prediction, not into the critic's weights.
        with frozen(self.critic):
            logits = up(self.critic(fake))
        loss = ((logits - 1.0) ** 2).mean()
        return loss if self.active else loss * 0.0

    # -- the critic's own step -------------------------------------------------------------------------------------
    @property
    def optimizer(self) -> torch.optim.Optimizer:
        # Built on first use, after Lightning has placed the critic on its device.
        if self._optimizer is None:
            self._optimizer = torch.optim.Adam(self.critic.parameters(), lr=self.lr, betas=self.betas)
            if self._pending_state is not None:
                self._optimizer.load_state_dict(self._pending_state)
                self._pending_state = None
        return self._optimizer

    def critic_loss(self, out: Outputs, batch: Batch) -> dict[str, torch.Tensor]:
        """LSGAN critic loss on the target and the detached prediction: {"d_loss", "d_real", "d_fake"} (scalars)."""
        fake = self.prediction(out).detach()
        real = to_model_range(batch["tgt"]).to(fake.dtype)
        d_real, d_fake = ((up(self.critic(real)) - 1.0) ** 2).mean(), (up(self.critic(fake)) ** 2).mean()
        return {"d_loss": d_real + d_fake, "d_real": d_real, "d_fake": d_fake}

    def update_critic(self, out: Outputs, batch: Batch) -> dict[str, torch.Tensor]:
        """One optimiser step of the critic (called by the module once per training step, before the losses).

        -> the critic's losses of this step, detached, for logging (empty before ``start_step``).
        """
        self.steps += 1
        if int(self.steps) <= self.start_step:
            return {}
        with torch.enable_grad():
            values = self.critic_loss(out, batch)
            opt = self.optimizer
            opt.zero_grad(set_to_none=True)
            values["d_loss"].backward()
            opt.step()
        return {k: v.detach() for k, v in values.items()}

    # -- checkpoints: the critic's weights are parameters; its optimiser state travels as extra state --------------
    def get_extra_state(self) -> dict:
        state = self._optimizer.state_dict() if self._optimizer is not None else self._pending_state
        return {"optimizer": state}

    def set_extra_state(self, state: dict) -> None:
        saved = (state or {}).get("optimizer")
        if saved is None:
            return
        if self._optimizer is not None:
            self._optimizer.load_state_dict(saved)
        else:
            self._pending_state = saved
