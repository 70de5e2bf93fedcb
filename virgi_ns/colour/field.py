"""The colour field of a frozen Gaussian scene: hash-grid features, diffuse and specular MLPs.

Every Gaussian gets features ``f = H(mean)`` from a multi-resolution hash grid over the
contracted scene box. Two small MLPs read them:

- ``MLP_diff``:  ``h1 = relu(A1 f)``, ``h2 = relu(A2 h1)``, ``c_d = diffuse_head(h2)``
  (``h2`` is ``h_diff``, the input of the segmentation head; ``diffuse_head`` is the layer an
  edit fine-tunes).
- ``MLP_spec``:  ``s1 = relu(B1 [f, SH(d)])``, ``s2 = relu(B2 [s1, h1])``, ``c_s = B3 [s2, h2]``.
  The one-way residual links are concatenations: layer 1 of MLP_diff feeds layer 2 of
  MLP_spec, layer 2 of MLP_diff feeds layer 3 of MLP_spec. Nothing flows from MLP_spec into
  MLP_diff's forward pass (gradients of the specular branch do reach MLP_diff's first two
  layers through the links; the diffuse head never sees the specular branch).
- colour ``C = sigmoid(c_d + c_s)``.

``B3`` starts at zero, so a fresh field is purely diffuse and the specular branch grows only
where the data asks for it.

With ``decoupled=False`` the field is the single-MLP baseline: one MLP of the same depth reads
``[f, SH(d)]`` and its output is ``c_d``; ``c_s`` is identically zero. Its hidden layers then
depend on the view direction, so :meth:`DecoupledColourField.diffuse_hidden` needs ``dirs``.

The field knows nothing of rendering; it maps positions (and directions) to colours.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Float
from nerfstudio.field_components.encodings import SHEncoding
from nerfstudio.field_components.spatial_distortions import SceneContraction
from torch import Tensor, nn

from virgi_ns.colour.encodings import GridEncoding


def _plus_part(layer: Tensor, part: Tensor) -> Tensor:
    """``layer + part``, in place on the layer's fresh output where ``part`` broadcasts into its shape (the
    same sums without a temporary: [N,1,H] parts over [N,P,H] directions); a new tensor otherwise (one
    direction shared by N parts)."""
    fits = part.dim() <= layer.dim() and all(p in (1, n) for p, n in zip(reversed(part.shape), reversed(layer.shape)))
    return layer.add_(part) if fits else layer + part


@dataclass
class ColourFieldConfig:
    """Hash grid and MLP sizes (Compact-3DGS's grid by default)."""

    levels: int = 16
    """Hash grid levels."""
    features_per_level: int = 2
    """Features per level (the encoding is ``levels * features_per_level`` wide)."""
    log2_hashmap_size: int = 19
    """log2 of the table size per level."""
    base_res: int = 16
    """Resolution of the coarsest level."""
    growth: float = 1.447
    """Per-level resolution factor; the finest level is ``base_res * growth ** (levels - 1)``."""
    hidden: int = 64
    """Width of every hidden layer."""
    sh_dir_degree: int = 4
    """View-direction encoding: SH bands ``0 .. sh_dir_degree - 1`` (1..4; nerfstudio's ``SHEncoding``), which gives
    ``sh_dir_degree ** 2`` components (4 -> 16, SH bands 0..3)."""
    decoupled: bool = True
    """Diffuse + specular branches (True) or the single view-dependent MLP baseline (False)."""
    residual_links: bool = True
    """Feed MLP_diff's hidden layers into MLP_spec's layers 2 and 3 (concatenation)."""

    @property
    def max_res(self) -> int:
        return int(round(self.base_res * self.growth ** max(self.levels - 1, 0)))


ColorFieldConfig = ColourFieldConfig
"""The class under the name a run's ``config.yml`` may give it (``virgi_ns.colour.field.ColorFieldConfig``)."""


class DecoupledColourField(nn.Module):
    """Per-point colour ``sigmoid(c_d + c_s)`` from hash features and a view direction."""

    def __init__(self, cfg: ColourFieldConfig, aabb: Float[Tensor, "2 3"], empty: bool = False) -> None:
        """``empty``: leave the hash table uninitialised, for a field whose trained state is loaded next."""
        super().__init__()
        self.cfg = cfg
        aabb = torch.as_tensor(aabb, dtype=torch.float32).reshape(2, 3)
        if not bool((aabb[1] > aabb[0]).all()):
            raise ValueError(f"DecoupledColourField: empty scene box {aabb.tolist()}")
        self.register_buffer("aabb", aabb.clone())
        self.hash = GridEncoding(
            num_levels=cfg.levels,
            min_res=cfg.base_res,
            max_res=max(cfg.max_res, cfg.base_res),
            log2_hashmap_size=cfg.log2_hashmap_size,
            features_per_level=cfg.features_per_level,
            implementation="torch",
            empty=empty,
        )
        self.contraction = SceneContraction(order=float("inf"))
        self.dir_encoding = SHEncoding(levels=cfg.sh_dir_degree, implementation="torch")
        f = self.hash.get_out_dim()
        d = self.dir_encoding.get_out_dim()
        h = cfg.hidden
        self.feature_dim = f
        self.dir_dim = d

        # MLP_diff (or the single MLP, which also reads the direction encoding)
        self.diffuse_l1 = nn.Linear(f if cfg.decoupled else f + d, h)
        self.diffuse_l2 = nn.Linear(h, h)
        self.diffuse_head = nn.Linear(h, 3)

        if cfg.decoupled:
            link = h if cfg.residual_links else 0
            self.spec_l1 = nn.Linear(f + d, h)
            self.spec_l2 = nn.Linear(h + link, h)
            self.spec_l3 = nn.Linear(h + link, 3)
            nn.init.zeros_(self.spec_l3.weight)
            nn.init.zeros_(self.spec_l3.bias)

    # ------------------------------------------------------------------ pieces
    @property
    def decoupled(self) -> bool:
        return self.cfg.decoupled

    def normalized_positions(self, positions: Float[Tensor, "N 3"]) -> Float[Tensor, "N 3"]:
        """Scene box -> [-1, 1]^3, contracted (L-inf) so that everything outside lands in
        [-2, 2]^3, then mapped to the hash grid's [0, 1]^3."""
        lo, hi = self.aabb[0], self.aabb[1]
        x = (positions - (lo + hi) / 2) / ((hi - lo) / 2)
        x = self.contraction(x)
        return ((x + 2.0) / 4.0).clamp(0.0, 1.0)

    def encode(self, positions: Float[Tensor, "N 3"]) -> Float[Tensor, "N F"]:
        """Hash-grid features of world positions."""
        x = self.normalized_positions(positions.to(self.aabb.dtype))
        return self.hash(x)

    def encode_dirs(self, dirs: Float[Tensor, "N 3"]) -> Float[Tensor, "N D"]:
        """SH encoding of unit view directions."""
        return self.dir_encoding(dirs)

    def diffuse_hidden(
        self, feats: Float[Tensor, "N F"], dirs: Float[Tensor, "N 3"] | None = None
    ) -> tuple[Float[Tensor, "N H"], Float[Tensor, "N H"]]:
        """(h1, h2) of MLP_diff; ``h2`` is ``h_diff``. The single-MLP baseline needs ``dirs``."""
        if self.cfg.decoupled:
            x = feats
        else:
            if dirs is None:
                raise ValueError("the single-MLP colour field needs view directions for its hidden layers")
            x = torch.cat([feats, self.encode_dirs(dirs).to(feats.dtype)], dim=-1)
        h1 = torch.relu(self.diffuse_l1(x))
        h2 = torch.relu(self.diffuse_l2(h1))
        return h1, h2

    def diffuse(self, h2: Float[Tensor, "N H"]) -> Float[Tensor, "N 3"]:
        """``c_d`` (pre-sigmoid) from ``h_diff``."""
        return self.diffuse_head(h2)

    def specular(
        self,
        feats: Float[Tensor, "N F"],
        dirs: Float[Tensor, "N 3"],
        h1: Float[Tensor, "N H"],
        h2: Float[Tensor, "N H"],
    ) -> Float[Tensor, "N 3"]:
        """``c_s`` (pre-sigmoid) of MLP_spec; zeros for the single-MLP baseline."""
        if not self.cfg.decoupled:
            return feats.new_zeros(feats.shape[0], 3)
        x = torch.cat([feats, self.encode_dirs(dirs).to(feats.dtype)], dim=-1)
        s1 = torch.relu(self.spec_l1(x))
        s2 = torch.relu(self.spec_l2(torch.cat([s1, h1], dim=-1) if self.cfg.residual_links else s1))
        return self.spec_l3(torch.cat([s2, h2], dim=-1) if self.cfg.residual_links else s2)

    # ------------------------------------------- MLP_spec split by what a view changes
    def specular_parts(
        self, feats: Float[Tensor, "N F"], h1: Float[Tensor, "N H"], h2: Float[Tensor, "N H"]
    ) -> tuple[Float[Tensor, "N H"], Float[Tensor, "N H"], Float[Tensor, "N 3"]]:
        """The parts of MLP_spec's three pre-activations that do not depend on the view direction:
        ``B1``'s feature columns times ``f`` plus its bias, ``B2``'s link columns times ``h1`` plus
        its bias, ``B3``'s link columns times ``h2`` plus its bias. A renderer keeps them per
        Gaussian and finishes with :meth:`specular_from_parts` when only the direction changes."""
        if not self.cfg.decoupled:
            raise ValueError("the single-MLP colour field has no specular branch")
        n, f, h = feats.shape[0], self.feature_dim, self.cfg.hidden
        p1 = nn.functional.linear(feats, self.spec_l1.weight[:, :f], self.spec_l1.bias)
        if self.cfg.residual_links:
            p2 = nn.functional.linear(h1, self.spec_l2.weight[:, h:], self.spec_l2.bias)
            p3 = nn.functional.linear(h2, self.spec_l3.weight[:, h:], self.spec_l3.bias)
        else:
            p2 = self.spec_l2.bias.expand(n, h)
            p3 = self.spec_l3.bias.expand(n, 3)
        return p1, p2, p3

    def specular_direction_weights(self) -> tuple[Float[Tensor, "H D"], Float[Tensor, "H H"], Float[Tensor, "3 H"]]:
        """The weights :meth:`specular_from_parts` applies per view: ``B1``'s direction columns,
        ``B2``'s columns on ``s1`` and ``B3``'s columns on ``s2``."""
        f, h = self.feature_dim, self.cfg.hidden
        return self.spec_l1.weight[:, f:], self.spec_l2.weight[:, :h], self.spec_l3.weight[:, :h]

    def specular_from_parts(
        self, p1: Float[Tensor, "N H"], p2: Float[Tensor, "N H"], p3: Float[Tensor, "N 3"], dirs: Float[Tensor, "N 3"]
    ) -> Float[Tensor, "N 3"]:
        """``c_s`` from :meth:`specular_parts` and unit view directions (equals :meth:`specular`)."""
        w_dir, w_s1, w_s2 = self.specular_direction_weights()
        s1 = torch.relu_(_plus_part(nn.functional.linear(self.encode_dirs(dirs).to(p1.dtype), w_dir), p1))
        s2 = torch.relu_(_plus_part(nn.functional.linear(s1, w_s1), p2))
        return _plus_part(nn.functional.linear(s2, w_s2), p3)

    # ----------------------------------------------------------------- forward
    def forward(self, positions: Float[Tensor, "N 3"], dirs: Float[Tensor, "N 3"]) -> dict[str, Tensor]:
        """``c_d``, ``c_s`` (pre-sigmoid, [N,3]) and ``rgb = sigmoid(c_d + c_s)``."""
        feats = self.encode(positions)
        h1, h2 = self.diffuse_hidden(feats, dirs)
        c_d = self.diffuse(h2)
        c_s = self.specular(feats, dirs, h1, h2)
        return {"c_d": c_d, "c_s": c_s, "rgb": torch.sigmoid(c_d + c_s)}

    def mlp_parameters(self) -> list[nn.Parameter]:
        """Every parameter except the hash table."""
        return [p for n, p in self.named_parameters() if not n.startswith("hash.")]

    def grid_parameters(self) -> list[nn.Parameter]:
        """The hash table."""
        return list(self.hash.parameters())


# nerfstudio's real SH basis (``SHEncoding``, bands 0..3) as polynomials in the direction's
# components: per output component, {(powers of x, y, z): coefficient}
_SH_POLYNOMIALS = (
    {(0, 0, 0): 0.28209479177387814},
    {(0, 1, 0): 0.4886025119029199},
    {(0, 0, 1): 0.4886025119029199},
    {(1, 0, 0): 0.4886025119029199},
    {(1, 1, 0): 1.0925484305920792},
    {(0, 1, 1): 1.0925484305920792},
    {(0, 0, 2): 0.9461746957575601, (0, 0, 0): -0.31539156525251999},
    {(1, 0, 1): 1.0925484305920792},
    {(2, 0, 0): 0.5462742152960396, (0, 2, 0): -0.5462742152960396},
    {(2, 1, 0): 3 * 0.5900435899266435, (0, 3, 0): -0.5900435899266435},
    {(1, 1, 1): 2.890611442640554},
    {(0, 1, 2): 5 * 0.4570457994644658, (0, 1, 0): -0.4570457994644658},
    {(0, 0, 3): 5 * 0.3731763325901154, (0, 0, 1): -3 * 0.3731763325901154},
    {(1, 0, 2): 5 * 0.4570457994644658, (1, 0, 0): -0.4570457994644658},
    {(2, 0, 1): 1.445305721320277, (0, 2, 1): -1.445305721320277},
    {(3, 0, 0): 0.5900435899266435, (1, 2, 0): -3 * 0.5900435899266435},
)


def monomial_degree(levels: int) -> int:
    """The degree of the products :func:`direction_monomials` forms for an SH encoding of
    ``levels`` bands (at least 1)."""
    return max(levels - 1, 1)


def direction_monomials(dirs: Float[Tensor, "N 3"], degree: int) -> Float[Tensor, "N M"]:
    """Every product of ``degree`` factors taken from ``(1, x, y, z)``, ``M = 4 ** degree`` columns
    (each monomial of degree <= ``degree`` appears, some more than once): three element-wise
    products for degree 3, where the SH encoding takes dozens of small operations."""
    one = nn.functional.pad(dirs, (1, 0), value=1.0)  # [N, 4]
    out = one
    for _ in range(degree - 1):
        out = (out[:, :, None] * one[:, None, :]).reshape(dirs.shape[0], -1)
    return out


def sh_monomial_matrix(levels: int, dtype=torch.float64) -> Float[Tensor, "M D"]:
    """``A`` with ``SHEncoding(levels)(d) = direction_monomials(d, monomial_degree(levels)) @ A`` for
    unit ``d``: each SH component's coefficients, placed on one column of its monomial."""
    if not 1 <= levels <= 4:
        raise ValueError(f"SH levels must be 1..4, got {levels}")
    q = monomial_degree(levels)
    a = torch.zeros(4**q, levels**2, dtype=dtype)
    for comp, poly in enumerate(_SH_POLYNOMIALS[: levels**2]):
        for (px, py, pz), coef in poly.items():
            factors = [1] * px + [2] * py + [3] * pz  # indices into (1, x, y, z), padded with the 1
            factors += [0] * (q - len(factors))
            row = 0
            for i in factors:
                row = row * 4 + i
            a[row, comp] += coef
    return a


def view_directions(means: Float[Tensor, "N 3"], centers: Float[Tensor, "N 3"]) -> Float[Tensor, "N 3"]:
    """Unit directions from camera centres to points (the direction light travels to the eye,
    reversed: camera -> point, as nerfstudio's ray directions)."""
    d = means - centers
    return d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)


__all__ = ["ColorFieldConfig", "ColourFieldConfig", "DecoupledColourField", "GridEncoding", "direction_monomials", "monomial_degree",
           "sh_monomial_matrix", "view_directions"]
