"""DecoupledColourField: shapes, the one-way residual links, the baseline switch, the box mapping."""

from __future__ import annotations

import math

import pytest
import torch

from virgi_ns.colour.field import (
    ColourFieldConfig,
    DecoupledColourField,
    direction_monomials,
    monomial_degree,
    sh_monomial_matrix,
    view_directions,
)

AABB = torch.tensor([[-1.0, -2.0, 0.0], [1.0, 2.0, 4.0]])


def small(**kw) -> ColourFieldConfig:
    return ColourFieldConfig(log2_hashmap_size=12, **kw)


def rand_inputs(n: int = 64, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    pos = AABB[0] + (AABB[1] - AABB[0]) * torch.rand(n, 3, generator=g)
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return pos, dirs


def test_default_config_matches_compact3dgs_grid():
    cfg = ColourFieldConfig()
    assert (cfg.levels, cfg.features_per_level, cfg.log2_hashmap_size, cfg.base_res) == (16, 2, 19, 16)
    assert cfg.max_res == round(16 * 1.447**15)
    field = DecoupledColourField(cfg, AABB)
    assert field.hash.hash_table.shape == (16 * 2**19, 2)
    # the finest level's resolution follows from the growth factor
    assert abs(float(field.hash.scalings[-1]) - 16 * 1.447**15) <= 2.0
    assert field.feature_dim == 32 and field.dir_dim == 16


def glossy(seed: int):
    """(field, positions, directions, its outputs): a small field whose specular head is not zero."""
    torch.manual_seed(seed)
    field = DecoupledColourField(small(), AABB)
    torch.nn.init.normal_(field.spec_l3.weight, std=0.5)
    pos, dirs = rand_inputs()
    return field, pos, dirs, field(pos, dirs)


def test_shapes_and_colour_formula():
    field, pos, dirs, out = glossy(0)
    assert out["c_d"].shape == out["c_s"].shape == out["rgb"].shape == (64, 3)
    torch.testing.assert_close(out["rgb"], torch.sigmoid(out["c_d"] + out["c_s"]))
    assert out["c_s"].abs().max() > 0
    # the pieces compose to forward
    feats = field.encode(pos)
    assert feats.shape == (64, 32)
    h1, h2 = field.diffuse_hidden(feats)
    assert h1.shape == h2.shape == (64, 64)
    torch.testing.assert_close(field.diffuse_head(h2), out["c_d"])
    torch.testing.assert_close(field.specular(feats, dirs, h1, h2), out["c_s"])


def test_fresh_field_is_purely_diffuse():
    field = DecoupledColourField(small(), AABB)
    pos, dirs = rand_inputs()
    out = field(pos, dirs)
    assert torch.count_nonzero(out["c_s"]) == 0
    # diffuse does not depend on the direction
    out2 = field(pos, -dirs)
    torch.testing.assert_close(out["c_d"], out2["c_d"])


def test_residual_links_are_one_way():
    field, pos, dirs, out = glossy(1)
    # the diffuse colour has no gradient into the specular branch
    grads = torch.autograd.grad(out["c_d"].sum(), [field.spec_l1.weight, field.spec_l2.weight, field.spec_l3.weight],
                                allow_unused=True)
    assert all(g is None or torch.count_nonzero(g) == 0 for g in grads)
    # ... while the specular colour does depend on MLP_diff's layers 1 and 2 (the links) but not its head
    out = field(pos, dirs)
    g1, g2, gh = torch.autograd.grad(out["c_s"].sum(), [field.diffuse_l1.weight, field.diffuse_l2.weight,
                                                        field.diffuse_head.weight], allow_unused=True)
    assert g1 is not None and g1.abs().sum() > 0
    assert g2 is not None and g2.abs().sum() > 0
    assert gh is None or torch.count_nonzero(gh) == 0
    # the links are concatenations of 64 extra inputs on MLP_spec layers 2 and 3
    assert field.spec_l2.in_features == 128 and field.spec_l3.in_features == 128


def test_without_residual_links_spec_ignores_diffuse_mlp():
    torch.manual_seed(2)
    field = DecoupledColourField(small(residual_links=False), AABB)
    torch.nn.init.normal_(field.spec_l3.weight, std=0.5)
    pos, dirs = rand_inputs()
    out = field(pos, dirs)
    g = torch.autograd.grad(out["c_s"].sum(), [field.diffuse_l1.weight], allow_unused=True)[0]
    assert g is None or torch.count_nonzero(g) == 0
    assert field.spec_l2.in_features == 64


def test_single_mlp_baseline():
    torch.manual_seed(3)
    field = DecoupledColourField(small(decoupled=False), AABB)
    assert not any(n.startswith("spec_") for n, _ in field.named_parameters())
    pos, dirs = rand_inputs()
    out = field(pos, dirs)
    assert torch.count_nonzero(out["c_s"]) == 0
    torch.testing.assert_close(out["rgb"], torch.sigmoid(out["c_d"]))
    # its single MLP is view dependent
    assert (field(pos, -dirs)["c_d"] - out["c_d"]).abs().max() > 1e-6
    with pytest.raises(ValueError):
        field.diffuse_hidden(field.encode(pos))


def test_box_mapping_and_contraction():
    field = DecoupledColourField(small(), AABB)
    centre = AABB.mean(0, keepdim=True)
    torch.testing.assert_close(field.normalized_positions(centre), torch.full((1, 3), 0.5))
    torch.testing.assert_close(field.normalized_positions(AABB[1:2]), torch.full((1, 3), 0.75))
    torch.testing.assert_close(field.normalized_positions(AABB[0:1]), torch.full((1, 3), 0.25))
    # a point 10 half-extents out along x: L-inf contraction gives 2 - 1/10 along x, scaled others
    half = (AABB[1] - AABB[0]) / 2
    p = centre + torch.tensor([[10.0, 0.0, 0.0]]) * half
    expect = torch.tensor([[(2 - 0.1 + 2) / 4, 0.5, 0.5]])
    torch.testing.assert_close(field.normalized_positions(p), expect)
    far = centre + 1e6 * half
    assert bool((field.normalized_positions(far) <= 1.0).all())


def test_view_directions():
    means = torch.tensor([[0.0, 0.0, 5.0], [3.0, 4.0, 0.0]])
    centers = torch.zeros(2, 3)
    torch.testing.assert_close(view_directions(means, centers), torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]]))


def test_field_fits_a_view_dependent_colour():
    """Diffuse albedo plus a lobe along +z: the trained field reproduces it and puts the lobe in c_s."""
    torch.manual_seed(4)
    field = DecoupledColourField(small(), AABB)
    pos, _ = rand_inputs(256, seed=5)
    albedo = torch.sigmoid(torch.stack([pos[:, 0], pos[:, 1] * 0.5, -pos[:, 0]], dim=-1))
    opt = torch.optim.Adam(field.parameters(), lr=1e-2)
    first = last = math.nan
    for it in range(300):
        dirs = torch.nn.functional.normalize(torch.randn(256, 3), dim=-1)
        lobe = dirs[:, 2:3].clamp_min(0) ** 8
        target = (albedo + 0.5 * lobe).clamp(0, 1)
        out = field(pos, dirs)
        loss = (out["rgb"] - target).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if it == 0:
            first = loss.item()
        last = loss.item()
    assert last < 0.3 * first
    up = torch.tensor([[0.0, 0.0, 1.0]]).expand(256, 3)
    down = -up
    out_up, out_down = field(pos, up), field(pos, down)
    # looking along +z is brighter than along -z by about the lobe's strength
    gain = (out_up["rgb"] - out_down["rgb"]).mean().item()
    assert 0.25 < gain < 0.75


def _ngp_reference(table: torch.Tensor, scalings: torch.Tensor, T: int, x: torch.Tensor) -> torch.Tensor:
    """Independent float64 evaluation of the grid: per level, the eight corners' hashed rows
    (Instant-NGP's primes, nerfstudio's corner convention: weight ``offset`` on the ceil corner),
    trilinearly blended."""
    L = scalings.shape[0]
    F = table.shape[1]
    out = torch.zeros(x.shape[0], L, F, dtype=torch.float64)
    primes = (1, 2654435761, 805459861)
    for lvl in range(L):
        s = x.double() * float(scalings[lvl])
        lo, hi = torch.floor(s).long(), torch.ceil(s).long()
        o = s - torch.floor(s)
        for cx in (0, 1):
            for cy in (0, 1):
                for cz in (0, 1):
                    c = [hi[:, 0] if cx else lo[:, 0], hi[:, 1] if cy else lo[:, 1], hi[:, 2] if cz else lo[:, 2]]
                    h = (c[0] * primes[0]) ^ (c[1] * primes[1]) ^ (c[2] * primes[2])
                    row = h % T + lvl * T
                    w = (o[:, 0] if cx else 1 - o[:, 0]) * (o[:, 1] if cy else 1 - o[:, 1]) * \
                        (o[:, 2] if cz else 1 - o[:, 2])
                    out[:, lvl] += w[:, None] * table.double()[row]
    return out.reshape(x.shape[0], L * F)


def test_grid_encoding_matches_nerfstudio_and_a_float64_reference():
    """The grid's one-gather forward equals nerfstudio's torch HashEncoding bit for bit, both equal
    an independent float64 evaluation, and the index_add_ gradient of the table equals the
    gradient through nerfstudio's per-corner indexing."""
    from nerfstudio.field_components.encodings import HashEncoding

    field = DecoupledColourField(small(levels=6, base_res=4, growth=2.0), AABB)
    ours = field.hash
    kw = dict(num_levels=6, min_res=4, max_res=ours.scalings[-1].item(), log2_hashmap_size=12, features_per_level=2,
              implementation="torch")
    theirs = HashEncoding(**kw)
    theirs.load_state_dict(ours.state_dict())
    assert torch.equal(theirs.scalings, ours.scalings)
    g = torch.Generator().manual_seed(3)
    x = torch.rand(500, 3, generator=g)
    x[:5] = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.5, 0.25, 0.75], [1.0, 0.0, 0.5], [0.125, 0.5, 1.0]])
    a, b = ours(x), theirs(x)
    assert torch.equal(a, b)
    ref = _ngp_reference(ours.hash_table.detach(), ours.scalings, 2**12, x)
    assert (a.double() - ref).abs().max() < 1e-6
    w = torch.randn(a.shape, generator=g)
    (a * w).sum().backward()
    (b * w).sum().backward()
    assert ours.hash_table.grad.abs().max() > 0.1
    assert torch.allclose(ours.hash_table.grad, theirs.hash_table.grad, atol=1e-5, rtol=0)


@pytest.mark.parametrize("links", [True, False])
def test_specular_split_by_what_a_view_changes(links):
    """MLP_spec from its direction-independent parts plus the per-view rest equals MLP_spec."""
    torch.manual_seed(0)
    field = DecoupledColourField(small(residual_links=links), AABB).double()
    for layer in (field.spec_l1, field.spec_l2, field.spec_l3):
        torch.nn.init.normal_(layer.weight, std=0.3)
        torch.nn.init.normal_(layer.bias, std=0.3)
    pos, dirs = rand_inputs()
    f = field.encode(pos.double())
    h1, h2 = field.diffuse_hidden(f)
    want = field.specular(f, dirs.double(), h1, h2)
    got = field.specular_from_parts(*field.specular_parts(f, h1, h2), dirs.double())
    assert want.abs().max() > 0.1
    torch.testing.assert_close(got, want, rtol=0, atol=1e-6)  # the SH encoding itself is float32


@pytest.mark.parametrize("levels", [1, 2, 3, 4])
def test_sh_encoding_as_direction_monomials(levels):
    """nerfstudio's SH encoding is a fixed linear map of the direction monomials."""
    from nerfstudio.field_components.encodings import SHEncoding

    _, dirs = rand_inputs(256, seed=levels)
    d = dirs.double()
    want = SHEncoding(levels=levels)(d).double()  # computed in float32 by nerfstudio
    got = direction_monomials(d, monomial_degree(levels)) @ sh_monomial_matrix(levels)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-7)


def test_grid_encoding_equals_nerfstudios_and_an_empty_one_loads_its_state():
    """The grid's one-``index_select`` forward gives nerfstudio's ``HashEncoding`` output bit for bit
    and its gradient to rounding (atomic adds sum in another order) on the same table;
    ``empty=True`` (no full-size random table) has the same scalings, offsets and state dict, and
    after loading the state computes the same."""
    from nerfstudio.field_components.encodings import HashEncoding

    from virgi_ns.colour.encodings import GridEncoding

    kw = dict(num_levels=5, min_res=4, max_res=64, log2_hashmap_size=10, features_per_level=2, implementation="torch")
    torch.manual_seed(11)
    ours = GridEncoding(**kw)
    torch.manual_seed(11)
    theirs = HashEncoding(**kw)
    assert torch.equal(ours.hash_table, theirs.hash_table)
    p = torch.rand(200, 3, generator=torch.Generator().manual_seed(5))
    a, b = ours(p), theirs(p)
    assert torch.equal(a, b)
    w = torch.randn_like(a)
    (a * w).sum().backward()
    (b * w).sum().backward()
    torch.testing.assert_close(ours.hash_table.grad, theirs.hash_table.grad, rtol=1e-6, atol=1e-6)  # summation order

    empty = GridEncoding(**kw, empty=True)
    assert empty.hash_table.device.type == "cpu" and empty.hash_table.shape == theirs.hash_table.shape
    assert torch.equal(empty.scalings, theirs.scalings) and torch.equal(empty.hash_offset, theirs.hash_offset)
    assert list(empty.state_dict()) == list(theirs.state_dict()) == ["hash_table"]
    empty.load_state_dict(theirs.state_dict())
    assert torch.equal(empty(p), theirs(p))
