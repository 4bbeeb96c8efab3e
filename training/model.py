"""The networks (paper Appendix A), in PyTorch.

All networks are MLPs of ``layers`` Linear layers with ELU between them and
dropout 0.1 before each Linear. Inputs and outputs are normalised with train
split statistics held as buffers, so an exported model maps raw features to
raw features.
"""
from __future__ import annotations

import torch
from torch import nn


def mlp(n_in: int, n_out: int, hidden: int, layers: int = 6, dropout: float = 0.1) -> nn.Sequential:
    mods = []
    d = n_in
    for i in range(layers):
        last = i == layers - 1
        mods += [nn.Dropout(dropout), nn.Linear(d, n_out if last else hidden)]
        if not last:
            mods.append(nn.ELU())
        d = hidden
    return nn.Sequential(*mods)


class Normalizer(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("std", torch.ones(dim))

    def fit(self, x: torch.Tensor):
        self.mean.copy_(x.mean(0))
        s = x.std(0)
        self.std.copy_(torch.where(s > 1e-4, s, torch.ones_like(s)))

    def norm(self, x):
        return (x - self.mean) / self.std

    def denorm(self, x):
        return x * self.std + self.mean


class MappingNet(nn.Module):
    """Leader's past 0.5 s of three points -> both dancers' future 1 s."""

    def __init__(self, n_in, n_out, hidden, layers=6, noise=0.1):
        super().__init__()
        self.nx, self.ny = Normalizer(n_in), Normalizer(n_out)
        self.net = mlp(n_in, n_out, hidden, layers)
        self.noise = noise

    def loss(self, x, y):
        xn = self.nx.norm(x)
        if self.training and self.noise > 0:
            xn = xn + self.noise * torch.randn_like(xn)
        return {"rec": ((self.net(xn) - self.ny.norm(y)) ** 2).mean()}

    def forward(self, x):
        return self.ny.denorm(self.net(self.nx.norm(x)))


class TrackingNet(nn.Module):
    """Codebook matching with a continuous latent (paper §4.2).

    Training: encoder E([x, y]) -> z_e, decoder D(z_e, x) -> y (L_rec), estimator
    S(x) -> z_s with L_matching = |z_e − z_s|². Inference: D(S(x), x).
    The latent is ``channels × width`` with a softmax over each channel.
    ``condition_decoder``: the decoder also sees the (normalised) input, so the
    latent carries what the input leaves open instead of the whole pose.
    """

    def __init__(self, n_in, n_out, hidden, layers=6, channels=16, width=32, noise=0.1,
                 condition_decoder=True):
        super().__init__()
        self.nx, self.ny = Normalizer(n_in), Normalizer(n_out)
        self.channels, self.width = channels, width
        z = channels * width
        self.estimator = mlp(n_in, z, hidden, layers)
        self.encoder = mlp(n_in + n_out, z, hidden, layers)
        self.condition = condition_decoder
        self.decoder = mlp(z + (n_in if condition_decoder else 0), n_out, hidden, layers)
        self.noise = noise

    def _decode(self, z, xn):
        return self.decoder(torch.cat([z, xn], dim=-1) if self.condition else z)

    def _latent(self, h):
        return torch.softmax(h.view(-1, self.channels, self.width), dim=-1).view(-1, self.channels * self.width)

    def loss(self, x, y):
        xn, yn = self.nx.norm(x), self.ny.norm(y)
        if self.training and self.noise > 0:
            xn = xn + self.noise * torch.randn_like(xn)
        z_e = self._latent(self.encoder(torch.cat([xn, yn], dim=-1)))
        z_s = self._latent(self.estimator(xn))
        rec = ((self._decode(z_e, xn) - yn) ** 2).mean()
        match = ((z_e - z_s) ** 2).sum(-1).mean()
        return {"rec": rec, "match": match}

    def forward(self, x):
        xn = self.nx.norm(x)
        return self.ny.denorm(self._decode(self._latent(self.estimator(xn)), xn))


class VanillaTracker(nn.Module):
    """Ablation (a): encoder and decoder stacked as one MLP, no latent, L_rec only."""

    def __init__(self, n_in, n_out, hidden, layers=6, noise=0.1):
        super().__init__()
        self.nx, self.ny = Normalizer(n_in), Normalizer(n_out)
        self.net = nn.Sequential(mlp(n_in, hidden, hidden, layers), nn.ELU(), mlp(hidden, n_out, hidden, layers))
        self.noise = noise

    def loss(self, x, y):
        xn = self.nx.norm(x)
        if self.training and self.noise > 0:
            xn = xn + self.noise * torch.randn_like(xn)
        return {"rec": ((self.net(xn) - self.ny.norm(y)) ** 2).mean()}

    def forward(self, x):
        return self.ny.denorm(self.net(self.nx.norm(x)))
