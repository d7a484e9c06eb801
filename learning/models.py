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
    # Channel widths of the three encoder stages.
    channels: tuple[int, int, int] = (16, 32, 48)
    # Softmax temperature of the spatial soft-argmax.
    temperature: float = 1.0


class KeypointNet(nn.Module):
    """f_R: fully convolutional, (mask, height) images -> M heatmaps -> pixel
    coordinates by a spatial soft-argmax (sub-pixel, differentiable).

    Input (B, 2, H, W): channel 0 the fabric mask in {0, 1}, channel 1 the
    height above the table (m) on the fabric, 0 elsewhere. Output (B, M, 2)
    pixel coordinates (u, v) in the input image.
    """

    def __init__(self, config: KeypointNetConfig):
        super().__init__()
        self.config = config
        c1, c2, c3 = config.channels

        def block(cin, cout, stride=1, dilation=1):
            return nn.Sequential(
                nn.Conv2d(cin, cout, 3, stride, padding=dilation, dilation=dilation),
                nn.BatchNorm2d(cout),
                nn.ReLU(inplace=True),
            )

        self.enc1 = nn.Sequential(block(2, c1), block(c1, c1))
        self.enc2 = nn.Sequential(block(c1, c2, 2), block(c2, c2))
        self.enc3 = nn.Sequential(
            block(c2, c3, 2), block(c3, c3, dilation=2), block(c3, c3, dilation=4)
        )
        self.dec2 = nn.Sequential(block(c3 + c2, c2), block(c2, c2))
        self.head = nn.Conv2d(c2, config.num_keypoints, 1)

    def heatmaps(self, x: torch.Tensor) -> torch.Tensor:
        s = self.config.input_stride
        if s > 1:
            x = F.avg_pool2d(x, s)
        e1 = self.enc1(x)
        e2 = self.enc2(e1)
        e3 = self.enc3(e2)
        up = F.interpolate(e3, size=e2.shape[-2:], mode="bilinear", align_corners=False)
        return self.head(self.dec2(torch.cat([up, e2], 1)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        H, W = x.shape[-2:]
        logits = self.heatmaps(x)
        B, M, h, w = logits.shape
        prob = torch.softmax(logits.reshape(B, M, -1) / self.config.temperature, -1)
        # Centres of the heatmap cells in input-pixel units.
        ys = (torch.arange(h, dtype=x.dtype) + 0.5) * (H / h) - 0.5
        xs = (torch.arange(w, dtype=x.dtype) + 0.5) * (W / w) - 0.5
        gy, gx = torch.meshgrid(ys, xs, indexing="ij")
        u = (prob * gx.reshape(-1)).sum(-1)
        v = (prob * gy.reshape(-1)).sum(-1)
        return torch.stack([u, v], -1)


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
