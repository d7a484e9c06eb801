"""Networks: the keypoint FCN f_R and the MLPs f_D, f_I (and f_A, baselines)."""

import dataclasses as dc

import torch
from torch import nn
from torch.nn import functional as F  # noqa: N812 (torch's own idiom)


@dc.dataclass
class KeypointNetConfig:
    num_keypoints: int = 8
    # Input images are average-pooled by this factor before the network.
    input_stride: int = 2
    # Channel widths of the three encoder stages (each halves the resolution).
    channels: tuple[int, int, int] = (16, 32, 64)
    # Softmax temperature of the spatial soft-argmax.
    temperature: float = 1.0


def _block(cin: int, cout: int, stride: int = 1, dilation: int = 1) -> nn.Module:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride, padding=dilation, dilation=dilation),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class KeypointNet(nn.Module):
    """f_R: fully convolutional, (mask, height) images -> M heatmaps -> pixel
    coordinates by a spatial soft-argmax (sub-pixel, differentiable).

    A small U-Net: three stride-2 stages (to 1/8 of the pooled input, the
    last one dilated for context) and two decoder stages back to 1/2, where
    the heatmaps live. Input (B, 2, H, W): channel 0 the fabric mask in
    {0, 1}, channel 1 the height above the table (scaled) on the fabric, 0
    elsewhere. Output (B, M, 2) pixel coordinates (u, v) in the input image.
    """

    def __init__(self, config: KeypointNetConfig):
        super().__init__()
        self.config = config
        c1, c2, c3 = config.channels
        self.enc1 = nn.Sequential(_block(2, c1, 2), _block(c1, c1))
        self.enc2 = nn.Sequential(_block(c1, c2, 2), _block(c2, c2))
        self.enc3 = nn.Sequential(_block(c2, c3, 2), _block(c3, c3, dilation=2))
        self.dec2 = _block(c3 + c2, c2)
        self.dec1 = nn.Sequential(_block(c2 + c1, c1), _block(c1, c1))
        self.head = nn.Conv2d(c1, config.num_keypoints, 1)

    def heatmaps(self, x: torch.Tensor) -> torch.Tensor:
        s = self.config.input_stride
        if s > 1:
            x = F.avg_pool2d(x, s)
        e1 = self.enc1(x)
        e2 = self.enc2(e1)
        e3 = self.enc3(e2)

        def up(a, like):
            return F.interpolate(
                a, size=like.shape[-2:], mode="bilinear", align_corners=False
            )

        d2 = self.dec2(torch.cat([up(e3, e2), e2], 1))
        return self.head(self.dec1(torch.cat([up(d2, e1), e1], 1)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self._soft_argmax(x, with_spread=False)[0]

    def locate(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, M, 2) pixel coordinates (the soft-argmax, as `forward`) and
        (B, M) their spread [px]: the standard deviation of each keypoint's
        heatmap distribution, small where f_R is sure of a keypoint."""
        return self._soft_argmax(x, with_spread=True)

    def _soft_argmax(self, x: torch.Tensor, *, with_spread: bool):
        H, W = x.shape[-2:]
        logits = self.heatmaps(x)
        B, M, h, w = logits.shape
        prob = torch.softmax(logits.reshape(B, M, -1) / self.config.temperature, -1)
        # Centres of the heatmap cells in input-pixel units.
        ys = (torch.arange(h, dtype=x.dtype) + 0.5) * (H / h) - 0.5
        xs = (torch.arange(w, dtype=x.dtype) + 0.5) * (W / w) - 0.5
        gy, gx = torch.meshgrid(ys, xs, indexing="ij")
        gx, gy = gx.reshape(-1), gy.reshape(-1)
        u = (prob * gx).sum(-1)
        v = (prob * gy).sum(-1)
        uv = torch.stack([u, v], -1)
        if not with_spread:  # training and the control loop: no spread needed
            return uv, None
        var = (prob * ((gx - u[..., None]) ** 2 + (gy - v[..., None]) ** 2)).sum(-1)
        return uv, var.clamp(min=0).sqrt()


@dc.dataclass
class MlpConfig:
    hidden: int = 256
    layers: int = 2


class Mlp(nn.Module):
    """Two hidden layers of 256 with ReLU (the paper's f_D, f_I, f_A)."""

    def __init__(self, n_in: int, n_out: int, config: MlpConfig | None = None):
        super().__init__()
        config = config or MlpConfig()
        dims = [n_in] + [config.hidden] * config.layers
        layers: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:], strict=True):
            layers += [nn.Linear(a, b), nn.ReLU()]
        layers.append(nn.Linear(dims[-1], n_out))
        self.net = nn.Sequential(*layers)
        self.n_in, self.n_out = n_in, n_out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)
