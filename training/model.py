"""The networks (paper Appendix A), in PyTorch.

All networks are MLPs of ``layers`` Linear layers with ELU between them and
dropout 0.1 before each Linear; white noise N(0, 0.1) is added to the
normalised input while training. Inputs and outputs are normalised with train
split statistics held as buffers, so an exported model maps raw features to
raw features.

Trackers (``pose_dim`` set) predict the residual to the "nothing moves"
prediction: the root unchanged and the current pose at every future key.
"""
from __future__ import annotations

import torch
from torch import nn

from dancing_points_addon import features as F
from dancing_points_addon.partner_pose import HIP_BINS
from dancing_points_addon.skeleton import LOWER_BODY


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


def pose_base(x: torch.Tensor, n_out: int, pose_dim: int) -> torch.Tensor:
    """Root unchanged ``(0, 0, 1, 0)`` and the current pose (the first ``pose_dim``
    input features, laid out like a key's pose block) at every future key."""
    # x[:, :4] * 0 + root: the batch size without shape arithmetic, so the
    # exported graph has no Shape/Expand/Where nodes (a tenth of a tracker's
    # run time at batch 1)
    root = x[:, :4] * 0.0 + x.new_tensor([0.0, 0.0, 1.0, 0.0])
    key = torch.cat([root, x[:, :pose_dim]], dim=1)
    k = n_out // (pose_dim + 4)
    return key if k == 1 else key.repeat(1, k)


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


class _Net(nn.Module):
    """Normalisation, optional residual target, input noise; subclasses define
    ``_loss(xn, yn)`` and ``_predict(xn)`` in normalised space."""

    def __init__(self, n_in, n_out, noise=0.1, pose_dim=None, pose_noise=0.0):
        super().__init__()
        self.nx, self.ny = Normalizer(n_in), Normalizer(n_out)
        self.n_out = n_out
        self.noise = noise
        self.pose_dim = pose_dim
        self.pose_noise = pose_noise

    def _rec(self, pred, target):
        return ((pred - target) ** 2).mean()

    def _base(self, x):
        return pose_base(x, self.n_out, self.pose_dim) if self.pose_dim else 0.0

    def fit_normalizers(self, x, y):
        """Statistics of the inputs and (residual) targets the loss will see,
        perturbed states included."""
        g = torch.get_rng_state()
        torch.manual_seed(1234)
        xc = self.corrupt_pose(x, force=True)
        torch.set_rng_state(g)
        self.nx.fit(xc)
        self.ny.fit(y - self._base(xc))

    # Perturbation scale of the current-pose input, per feature group, in the
    # features' own units: metres for positions, 6D entries, contact values.
    POSE_NOISE_UNITS = ((F.POSE_POS.start, F.POSE_POS.stop, 0.04), (F.POSE_ROT.start, F.POSE_ROT.stop, 0.08),
                        (F.POSE_CON.start, F.POSE_CON.stop, 0.3))

    def corrupt_pose(self, x, force=False):
        """Training only: perturb the *current pose* input with Gaussian noise whose
        standard deviation is drawn per sample from U(0, ``pose_noise``) ×
        :data:`POSE_NOISE_UNITS`. The residual base
        is built from the perturbed pose too, so the target teaches the network to
        pull a drifted state back to what the three-point keys say: in a
        closed-loop rollout the state is its own, imperfect, prediction."""
        if not ((self.training or force) and self.pose_dim and self.pose_noise > 0):
            return x
        scale = torch.rand(x.shape[0], 1, device=x.device) * self.pose_noise
        unit = torch.zeros(self.pose_dim, device=x.device)
        for a, b, u in self.POSE_NOISE_UNITS:
            unit[a:b] = u
        noise = torch.randn(x.shape[0], self.pose_dim, device=x.device) * unit * scale
        return torch.cat([x[:, :self.pose_dim] + noise, x[:, self.pose_dim:]], dim=1)

    def loss(self, x, y, w=None):
        """``w``: per-sample weights for the networks that take them (the mapping's,
        per dancer); None: every sample and output counts alike."""
        x = self.corrupt_pose(x)
        xn, yn = self.nx.norm(x), self.ny.norm(y - self._base(x))
        if self.training and self.noise > 0:
            xn = xn + self.noise * torch.randn_like(xn)
        return self._loss(xn, yn) if w is None else self._loss(xn, yn, w)

    def forward(self, x):
        return self.ny.denorm(self._predict(self.nx.norm(x))) + self._base(x)

    def output_layer(self) -> nn.Linear:
        raise NotImplementedError

    def truncated(self, keep) -> "_Net":
        """A copy whose last layer computes only the outputs ``keep`` (a prefix
        of whole keys for trackers): for inference, where later keys are unused."""
        import copy

        keep = torch.as_tensor(keep, dtype=torch.long)
        m = copy.deepcopy(self).eval()
        lin = m.output_layer()
        new = nn.Linear(lin.in_features, len(keep))
        with torch.no_grad():
            new.weight.copy_(lin.weight[keep])
            new.bias.copy_(lin.bias[keep])
        m.set_output_layer(new)
        m.ny = Normalizer(len(keep))
        m.ny.mean.copy_(self.ny.mean[keep])
        m.ny.std.copy_(self.ny.std[keep])
        m.n_out = len(keep)
        return m


class MappingNet(_Net):
    """Leader's past 0.5 s of three points -> both dancers' future 1 s."""

    # loss on the normalised outputs: "mse" (squared error: the conditional mean; the pose
    # anchor's) or "norm" (the Euclidean norm of each frame's position, heading and tracked
    # point per dancer, unsquared: a geometric median, what a mean distance rewards; the
    # mapping's and the placement network's)
    LOSSES = ("mse", "norm")

    def __init__(self, n_in, n_out, hidden, layers=6, noise=0.1, dropout=0.1, loss="mse"):
        super().__init__(n_in, n_out, noise)
        if loss not in self.LOSSES:
            raise ValueError(f"loss: one of {self.LOSSES}, not {loss!r}")
        if loss == "norm" and n_out % F.FRAME_DIM:
            raise ValueError(f"the norm loss needs whole frames of {F.FRAME_DIM} outputs, not {n_out}")
        self.loss_kind = loss
        self.net = mlp(n_in, n_out, hidden, layers, dropout)

    def _loss(self, xn, yn, w=None):
        return {"rec": self.map_loss(self.net(xn), yn, w)}

    # groups of one frame of one dancer: root position (x, z), heading (cos, sin), three points
    GROUPS = [(0, 2), (2, 4)] + [(F.ROOT_DIM + 3 * k, F.ROOT_DIM + 3 * k + 3) for k in range(3)]

    def map_loss(self, pred, yn, w=None):
        """The loss of normalised predictions ``pred`` against targets ``yn``;
        ``w`` (the norm loss only): each sample's weights of the leader's and of the
        follower's outputs (frames alternate leader, follower), ``(B, 2)``, or per
        group of :data:`GROUPS`, ``(B, 2, 5)``; None: all alike."""
        if self.loss_kind != "norm":  # (any output size: the pose anchor's)
            if w is not None:
                raise ValueError("per-sample weights need the norm loss")
            return self._rec(pred, yn)
        frames = self.n_out // F.FRAME_DIM
        d = (pred - yn).view(-1, frames, F.FRAME_DIM)
        norms = torch.stack([((d[..., a:b] ** 2).sum(-1) + 1e-12).sqrt() for a, b in self.GROUPS], -1)
        if w is None:
            return norms.mean()
        # (B, frames, groups): each frame-dancer-group's weight
        w = w[:, :, None].expand(-1, -1, len(self.GROUPS)) if w.dim() == 2 else w
        w = w[:, torch.arange(frames, device=w.device) % 2]
        return (norms * w).sum() / w.sum().clamp_min(1e-12)

    def _predict(self, xn):
        return self.net(xn)

    def output_layer(self):
        return self.net[-1]

    def set_output_layer(self, lin):
        self.net[-1] = lin


class PoseAnchorNet(MappingNet):
    """The follower's pose anchor: the mapping network's input (the
    leader's past 0.5 s of three points) -> her lower body at the current frame
    in her own hip frame (``representation.hip_frame``), ``(B, 30)``. An MLP
    trained on the squared error. It knows nothing of her previous frames: the
    runtime pulls her tracker's closed-loop legs a share of the way to it each
    frame (``PoseOptions.anchor``; models/README.md, "Pose anchor")."""

    def __init__(self, n_in, n_out=3 * len(LOWER_BODY), hidden=512, layers=3, noise=0.05, dropout=0.2):
        super().__init__(n_in, n_out, hidden, layers, noise, dropout)

    def truncated(self, keep=None) -> "PoseAnchorNet":
        return self  # every output is used


class ContactNet(nn.Module):
    """Foot contacts of both dancers: the mapping network's input (the
    leader's past 0.5 s of three points) -> the contact probability of the SPEC §2
    foot points of the leader and of the follower at the current frame, ``(B, 8)``.
    A small MLP (ELU, dropout), binary cross-entropy, white noise on the
    normalised input while training; the output is the probability (sigmoid in
    the graph). It gives the follower's foot lock its timing: her tracker's own
    contact output says "planted" on 88 % of the val frames, and steps taken when
    her lock drifts are no better than chance (models/README.md)."""

    def __init__(self, n_in, n_out=8, hidden=256, layers=3, noise=0.05, dropout=0.2):
        super().__init__()
        self.nx = Normalizer(n_in)
        self.noise = noise
        mods, d = [], n_in
        for _ in range(layers - 1):  # dropout after each hidden layer (not on the input)
            mods += [nn.Linear(d, hidden), nn.ELU(), nn.Dropout(dropout)]
            d = hidden
        self.net = nn.Sequential(*mods, nn.Linear(d, n_out))

    def fit_normalizers(self, x, y):
        self.nx.fit(x)

    def loss(self, x, y):
        xn = self.nx.norm(x)
        if self.training and self.noise > 0:
            xn = xn + self.noise * torch.randn_like(xn)
        return self._criterion(self.net(xn), y)

    @staticmethod
    def _criterion(logits, y):
        return {"bce": nn.functional.binary_cross_entropy_with_logits(logits, y)}

    def forward(self, x):
        return torch.sigmoid(self.net(self.nx.norm(x)))

    def truncated(self, keep=None) -> "ContactNet":
        return self  # every output is used


class HipHeadingNet(ContactNet):
    """The follower's hip heading: the mapping network's input (the
    leader's past 0.5 s of three points) -> the probabilities of her hip heading
    *relative to his root's heading* at the current frame over
    ``follower.HIP_BINS`` bins of the full turn, ``(B, HIP_BINS)`` (softmax in the
    graph). Cross-entropy on one-hot targets. The runtime turns her hips towards
    the bins' circular mean (``HipOptions``): a heading read from
    bins copes with the spins, where a regressed one averages a turn away."""

    def __init__(self, n_in, n_out=HIP_BINS, hidden=512, layers=3, noise=0.05, dropout=0.2):
        super().__init__(n_in, n_out, hidden, layers, noise, dropout)

    @staticmethod
    def _criterion(logits, y):
        return {"ce": nn.functional.cross_entropy(logits, y)}

    def forward(self, x):
        return torch.softmax(self.net(self.nx.norm(x)), dim=-1)


class TrackingNet(_Net):
    """Codebook matching with a continuous latent (paper §4.2).

    Training: encoder E([x, y]) -> z_e, decoder D(z_e, x) -> y (L_rec), estimator
    S(x) -> z_s with L_matching = |z_e − z_s|². Inference: D(S(x), x): an MLP.
    The latent is ``channels × width`` with a softmax over each channel. The
    decoder also sees the input, so the latent carries what the input leaves
    open rather than the whole pose.
    """

    def __init__(self, n_in, n_out, hidden, layers=6, channels=16, width=32, noise=0.1, pose_dim=None,
                 pose_noise=0.0):
        super().__init__(n_in, n_out, noise, pose_dim, pose_noise)
        self.channels, self.width = channels, width
        z = channels * width
        self.estimator = mlp(n_in, z, hidden, layers)
        self.encoder = mlp(n_in + n_out, z, hidden, layers)
        self.decoder = mlp(z + n_in, n_out, hidden, layers)

    def _decode(self, z, xn):
        return self.decoder(torch.cat([z, xn], dim=-1))

    def _latent(self, h):
        return torch.softmax(h.view(-1, self.channels, self.width), dim=-1).view(-1, self.channels * self.width)

    def _loss(self, xn, yn):
        z_e = self._latent(self.encoder(torch.cat([xn, yn], dim=-1)))
        z_s = self._latent(self.estimator(xn))
        rec = self._rec(self._decode(z_e, xn), yn)
        match = ((z_e - z_s) ** 2).sum(-1).mean()
        return {"rec": rec, "match": match}

    def _predict(self, xn):
        return self._decode(self._latent(self.estimator(xn)), xn)

    def output_layer(self):
        return self.decoder[-1]

    def set_output_layer(self, lin):
        self.decoder[-1] = lin


class VanillaTracker(_Net):
    """Ablation (a): encoder and decoder stacked as one MLP, no latent, L_rec only."""

    def __init__(self, n_in, n_out, hidden, layers=6, noise=0.1, pose_dim=None, pose_noise=0.0):
        super().__init__(n_in, n_out, noise, pose_dim, pose_noise)
        self.net = nn.Sequential(mlp(n_in, hidden, hidden, layers), nn.ELU(), mlp(hidden, n_out, hidden, layers))

    def _loss(self, xn, yn):
        return {"rec": self._rec(self.net(xn), yn)}

    def _predict(self, xn):
        return self.net(xn)

    def output_layer(self):
        return self.net[-1][-1]

    def set_output_layer(self, lin):
        self.net[-1][-1] = lin
