"""Flow + pixel aggregation baseline after Sun et al. (2018), single-input setting, layer for layer as their code."""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from nvs.core.types import RGB_BRANCHES, Batch, Outputs, to_image_range, to_model_range
from nvs.core.weight_init import xavier_convs
from nvs.models.baselines.common import POSE_DIM, BaselineOutputs, pose_code

# Decoder widths of Sun et al.'s joint decoder, stage by stage from the bottleneck up (its output layers use half
# of the last one).
DECODER_CHANNELS = (256, 128, 64, 32, 16, 8)


def lrelu() -> nn.Module:
    return nn.LeakyReLU(0.2)


def coordinate_channels(B: int, H: int, W: int, like: torch.Tensor) -> torch.Tensor:
    """Sun et al.'s image-coordinate channels: x = 2j/W - 1, y = 2i/H - 1 -> (B,2,H,W) (pixel j at -1 + 2j/W)."""
    xs = torch.arange(W, device=like.device, dtype=like.dtype) * (2.0 / W) - 1.0
    ys = torch.arange(H, device=like.device, dtype=like.dtype) * (2.0 / H) - 1.0
    return torch.stack([xs.view(1, W).expand(H, W), ys.view(H, 1).expand(H, W)]).expand(B, 2, H, W)


class OneStepConvLSTM(nn.Module):
    """A ConvLSTM cell run for one step from a zero state (the single-input case of Sun et al.'s recurrent blocks).

    With c_0 = h_0 = 0 the forget gate and the recurrent kernel have no effect, so only the input part of the
    3x3 kernel and the input, candidate and output gates remain: c = s(i) tanh(g), h = tanh(c) s(o).
    (B,C,h,w) -> (B,C,h,w).
    """

    def __init__(self, channels: int):
        super().__init__()
        self.gates = nn.Conv2d(channels, 3 * channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        i, g, o = self.gates(x).chunk(3, dim=1)
        return torch.tanh(torch.sigmoid(i) * torch.tanh(g)) * torch.sigmoid(o)


class ConvLSTMResidual(nn.Module):
    """x + lstm_2(lstm_1(x)), Sun et al.'s residual ConvLSTM block (no activation after the sum, no norm)."""

    def __init__(self, channels: int):
        super().__init__()
        self.lstm1, self.lstm2 = OneStepConvLSTM(channels), OneStepConvLSTM(channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.lstm2(self.lstm1(x))


class FlowResidual(nn.Module):
    """lrelu(conv3x3(x) + x): Sun et al.'s residual block as their code computes it.

    Their block's first conv feeds nothing (the second conv reads the block input, not the first conv's output),
    so it is left out here: same outputs, no parameters that never receive a gradient.
    """

    def __init__(self, channels: int):
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, padding=1)
        self.act = lrelu()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.conv(x) + x)


def up_stage(cin: int, cout: int, scale: int = 2) -> nn.Sequential:
    """Nearest-neighbour x``scale`` + 3x3 conv + ReLU (their ``nn_deconv2d`` without norm): (B,cin,h,w) -> (B,cout,sh,sw)."""
    layers = [nn.Upsample(scale_factor=scale, mode="nearest")] if scale > 1 else []
    return nn.Sequential(*layers, nn.Conv2d(cin, cout, 3, padding=1), nn.ReLU())


class SunEncoder(nn.Module):
    """[image, coordinates, tiled pose] -> features at S/2 ... S/2^n: 4x4 stride-2 convs with 32 * 2^i channels and
    LeakyReLU(0.2), no norm; the pixel module's ``lstm_scales`` innermost outputs pass ConvLSTM residual blocks.

    (B,3+2+POSE_DIM,S,S) -> [(B,32,S/2,S/2), ..., (B,32*2^(n-1),S/2^n,S/2^n)].
    """

    def __init__(self, in_channels: int, n_layers: int = 5, lstm_scales: int = 0, lstm_blocks: int = 2):
        super().__init__()
        chans = [2 ** (i + 5) for i in range(n_layers)]
        self.channels = chans
        self.convs = nn.ModuleList([nn.Sequential(nn.Conv2d(cin, cout, 4, stride=2, padding=1), lrelu())
                                    for cin, cout in zip([in_channels] + chans[:-1], chans)])
        # Scale s (0 = innermost) -> its blocks, applied to that encoder output (as their pixel module does).
        self.lstm = nn.ModuleList([nn.Sequential(*[ConvLSTMResidual(chans[n_layers - 1 - s])
                                                   for _ in range(lstm_blocks)]) for s in range(lstm_scales)])

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        feats = []
        for conv in self.convs:
            x = conv(x)
            feats.append(x)
        for s, blocks in enumerate(self.lstm):
            feats[-1 - s] = blocks(feats[-1 - s])
        return feats


class SunDecoder(nn.Module):
    """One branch of Sun et al.'s joint decoder: residual blocks at the bottleneck, then per stage (optionally)
    the encoder features of that resolution concatenated, nearest x2 + conv + ReLU; then a 3x3 conv + ReLU to half
    the last width and a linear 3x3 conv to ``out_channels``.

    encoder features [(B,C_i,S/2^(i+1),...)] -> (B,out_channels,S,S) raw.
    """

    def __init__(self, enc_channels: list[int], out_channels: int, n_res: int = 0, skips: bool = False):
        super().__init__()
        n = len(enc_channels)
        if n > len(DECODER_CHANNELS):
            raise ValueError(f"at most {len(DECODER_CHANNELS)} encoder layers, got {n}")
        width = DECODER_CHANNELS[:n]
        self.res = nn.Sequential(*[FlowResidual(enc_channels[-1]) for _ in range(n_res)])
        # Their pixel branch concatenates the encoder output of each stage's input resolution; at the bottleneck that
        # is the block input itself, skipped when there are no residual blocks (the case of their defaults).
        self.skip_at = [skips and (i > 0 or n_res > 0) for i in range(n)]
        cins = [(width[i - 1] if i else enc_channels[-1]) + (enc_channels[n - 1 - i] if self.skip_at[i] else 0)
                for i in range(n)]
        self.ups = nn.ModuleList([up_stage(cins[i], width[i]) for i in range(n)])
        self.out = nn.Sequential(up_stage(width[-1], width[-1] // 2, scale=1),
                                 nn.Conv2d(width[-1] // 2, out_channels, 3, padding=1))

    def forward(self, feats: list[torch.Tensor]) -> torch.Tensor:
        x = self.res(feats[-1])
        for i, stage in enumerate(self.ups):
            if self.skip_at[i]:
                x = torch.cat([x, feats[-1 - i]], dim=1)
            x = stage(x)
        return self.out(x)


def sample_flow(src: torch.Tensor, flow: torch.Tensor, padding_mode: str) -> torch.Tensor:
    """Sample ``src`` at pixel j + flow * W/2 (Sun et al.'s flow units): src (B,C,H,W), flow (B,2,H,W) -> (B,C,H,W).

    Their sampler puts pixel j at -1 + 2j/W and reads it at (x + 1) W/2, i.e. the pixel-centre grid of
    ``align_corners=False`` shifted by half a pixel; here the same displacement is added to that grid.
    """
    B, _, H, W = src.shape
    like = flow.float()
    xs = (torch.arange(W, device=src.device, dtype=like.dtype) * 2 + 1) / W - 1
    ys = (torch.arange(H, device=src.device, dtype=like.dtype) * 2 + 1) / H - 1
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1).expand(B, H, W, 2)
    # In bf16 the grid is off by up to 1/256 of the image: build it and add the flow in float32.
    grid = grid + like.permute(0, 2, 3, 1)
    return F.grid_sample(src, grid.to(src.dtype), mode="bilinear", padding_mode=padding_mode, align_corners=False)


class Sun(nn.Module):
    """Sun, Huh, Liao, Zhang, Lim, "Multi-view to Novel View: Synthesizing Novel Views with Self-Learned Confidence",
    ECCV 2018, in its single-input setting, as their code (``model.py``) builds it with its default configuration.

    Two modules with their own encoders see [image, pixel coordinates, the pose tiled as a map]: 5 stride-2 4x4
    convs (32..512 channels, LeakyReLU 0.2, no norm). The flow module has 4 residual blocks at the bottleneck and a
    decoder without skips (nearest x2 + conv + ReLU, 256..16 channels) ending in (flow x, flow y, confidence); the
    pixel module has residual ConvLSTM blocks (2 per scale) on its 3 innermost encoder outputs, skip connections to
    every decoder stage and ends in (tanh RGB, confidence). The two predictions are blended per pixel by a softmax
    over the two confidences. Xavier-uniform weights, zero biases.

    What differs (see docs/fidelity_baselines.md): one input view, so the ConvLSTM runs one step from a zero state;
    the pose is the relative [R|t] about the pivot, 12 numbers (their objects use one-hot view bins, their scenes a
    6-vector pose difference); images are [-1,1] without their inversion of object images (a sign their first and
    last layers absorb); any size divisible by 2^n_layers; one optimiser with two parameter groups (``param_groups``)
instead of their two Adams. The adversarial term on the pixel module is the
    ``adversarial`` loss term (``nvs.losses.adversarial``).

    forward(batch, needs) -> ``rgb`` (B,3,S,S) in [0,1], ``rgb_scales`` [(B,3,S,S) in [-1,1]], ``rgb_branches``
    {"flow", "pixel": (B,3,S,S) in [0,1]}, ``confidence`` (B,2,S,S) softmax weights (flow, pixel).
    """

    provides = frozenset({RGB_BRANCHES})
    n_scales = 1  # len(rgb_scales)

    def __init__(self, image_size: int, n_layers: int = 5, n_res_flow: int = 4, n_res_pixel: int = 0,
                 lstm_scales: int = 3, lstm_blocks: int = 2, padding_mode: str = "border",
                 pixel_lr_scale: float = 1.0, pixel_betas: tuple[float, float] | None = None):
        super().__init__()
        if image_size % 2 ** n_layers:
            raise ValueError(f"image_size={image_size} must be divisible by 2^n_layers = {2 ** n_layers}")
        if not 0 <= lstm_scales <= n_layers:
            raise ValueError(f"lstm_scales={lstm_scales} must be within 0..n_layers={n_layers}")
        if padding_mode not in ("border", "zeros"):
            raise ValueError(f"padding_mode={padding_mode!r}: expected 'border' or 'zeros'")
        self.padding_mode = padding_mode
        self.pixel_lr_scale = float(pixel_lr_scale)
        self.pixel_betas = tuple(float(b) for b in pixel_betas) if pixel_betas is not None else None
        cin = 3 + 2 + POSE_DIM
        self.flow_encoder = SunEncoder(cin, n_layers)
        self.pixel_encoder = SunEncoder(cin, n_layers, lstm_scales, lstm_blocks)
        chans = self.flow_encoder.channels
        self.flow_decoder = SunDecoder(chans, 3, n_res=n_res_flow, skips=False)  # flow (x, y) + confidence
        self.pixel_decoder = SunDecoder(chans, 4, n_res=n_res_pixel, skips=True)  # RGB + confidence
        xavier_convs(self)  # TF-slim's default initialiser

    def param_groups(self) -> list[dict]:
        """Optimiser groups: the flow module at the optimiser's settings, the pixel module at ``pixel_lr_scale`` times
        its lr and with ``pixel_betas`` (their two Adams: flow lr 1e-4, pixel lr 5e-5 with beta1 0.5 under the GAN)."""
        pixel = [p for m in (self.pixel_encoder, self.pixel_decoder) for p in m.parameters() if p.requires_grad]
        flow = [p for m in (self.flow_encoder, self.flow_decoder) for p in m.parameters() if p.requires_grad]
        group = {"params": pixel, "lr_scale": self.pixel_lr_scale}
        if self.pixel_betas is not None:
            group["betas"] = self.pixel_betas
        return [{"params": flow}, group]

    def forward(self, batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs:
        src = batch["src"]
        B, _, H, W = src.shape
        pose = pose_code(batch["T_tgt_src"], batch["pivot"]).to(src.dtype)
        x = torch.cat([to_model_range(src), coordinate_channels(B, H, W, src),
                       pose[:, :, None, None].expand(B, POSE_DIM, H, W)], dim=1)
        f = self.flow_decoder(self.flow_encoder(x))
        rgb_flow = sample_flow(src, f[:, :2], self.padding_mode)
        g = self.pixel_decoder(self.pixel_encoder(x))
        rgb_pixel = to_image_range(torch.tanh(g[:, :3]))
        w = torch.softmax(torch.cat([f[:, 2:], g[:, 3:]], dim=1).float(), dim=1).to(rgb_pixel.dtype)
        rgb = w[:, :1] * rgb_flow + w[:, 1:] * rgb_pixel
        return BaselineOutputs("sun", rgb=rgb, rgb_scales=[to_model_range(rgb)], confidence=w,
                               **{RGB_BRANCHES: {"flow": rgb_flow, "pixel": rgb_pixel}})
