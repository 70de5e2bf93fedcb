"""Both ways a pixel batch applies its sparse matrix (``EditConfig.batch_composite``: ``csr`` and ``fused``)
against a dense float64 oracle, through :func:`pixel_batches`, and in a whole edit against each other."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import edit_scene as es  # noqa: E402

from virgi_ns.edit.engine import EditConfig, EditEngine  # noqa: E402
from virgi_ns.edit.pixels import CompositeOp, pixel_batches  # noqa: E402
from virgi_ns.edit.recolor import RecolorRule, recolor  # noqa: E402
from virgi_ns.edit.scene import render_view  # noqa: E402

KINDS = ["csr", "fused"]


def random_entries(p: int = 200, U: int = 150, used: int = 120, max_per_row: int = 30, seed: int = 0):
    """Entries of a random sparse [p, U] matrix sorted by row: 0..max_per_row distinct Gaussians a row
    (some rows empty), drawn from the first ``used`` Gaussians only (the rest have no entry)."""
    g = torch.Generator().manual_seed(seed)
    n = torch.randint(0, max_per_row + 1, (p,), generator=g)
    n[::7] = 0
    rows = torch.repeat_interleave(torch.arange(p), n)
    cols = torch.cat([torch.randperm(used, generator=g)[: int(k)] for k in n])
    vals = torch.rand(rows.numel(), generator=g) * 0.9 + 0.05
    return rows, cols, vals


def dense(rows, cols, vals, p, U) -> torch.Tensor:
    return torch.zeros(p, U, dtype=torch.float64).index_put_((rows, cols), vals.double(), accumulate=True)


def rel_err(got: torch.Tensor, ref: torch.Tensor) -> float:
    return float((got.detach().double() - ref).abs().max() / ref.abs().max())


def test_composite_matches_dense_oracle():
    """Forward ``A @ C`` and the gradient ``A^T @ g`` equal a float64 dense product to float32 rounding."""
    p, U = 200, 150
    rows, cols, vals = random_entries(p, U)
    assert (rows.bincount(minlength=p) == 0).any() and (cols.bincount(minlength=U) == 0).any()
    A = dense(rows, cols, vals, p, U)
    op = CompositeOp(rows, cols, vals, p, U)
    g = torch.Generator().manual_seed(1)
    C = torch.rand(U, 3, generator=g, requires_grad=True)
    w = torch.randn(p, 3, generator=g)
    out = op(C)
    assert out.shape == (p, 3) and out.dtype == torch.float32
    assert rel_err(out, A @ C.detach().double()) < 2e-6
    (grad,) = torch.autograd.grad((out * w).sum(), C)
    assert grad.shape == (U, 3)
    assert rel_err(grad, A.T @ w.double()) < 2e-6
    unused = cols.bincount(minlength=U) == 0
    assert bool((grad[unused] == 0).all())


def test_composite_without_entries():
    """A batch that meets no Gaussian renders zeros and passes a zero gradient."""
    e = torch.zeros(0, dtype=torch.long)
    op = CompositeOp(e, e, torch.zeros(0), 4, 5)
    C = torch.rand(5, 3, requires_grad=True)
    out = op(C)
    assert out.shape == (4, 3) and bool((out == 0).all())
    (grad,) = torch.autograd.grad(out.sum(), C)
    assert bool((grad == 0).all())


DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("gathered", [True, False])
def test_fused_sets_match_a_dense_oracle(device, gathered):
    """The fused kind's loss of each pixel set and its gradient to the colours equal a float64 dense
    computation (the composite, the weighted L1 mean, its subgradient); the device counter takes the
    sets in turn and wraps. On a GPU this checks the CUDA kernels (the gradient gathered per Gaussian,
    or, without the sorted entries, scattered by atomics), on the CPU the torch reference."""
    P, U = 300, 150
    rows, cols, vals = random_entries(P, U, seed=4)
    dev = torch.device(device)
    contrib = SimpleNamespace(num_pixels=P, pair_gaussian=torch.arange(U), pixel=rows.to(dev), pair=cols.to(dev),
                              weight=vals.to(dev), transmittance=torch.rand(P).to(dev))
    g = torch.Generator().manual_seed(3)
    target, bg = torch.rand(P, 3, generator=g).to(dev), torch.tensor([0.2, 0.3, 0.4], device=dev)
    changed = (torch.rand(P, generator=g) < 0.2).to(dev)
    C = torch.rand(U, 3, generator=g).to(dev)
    A = dense(rows, cols, vals, P, U)
    for weighted in (False, True):
        batches = pixel_batches(contrib, target, bg, 3, 7, changed if weighted else None, 0.6, composite="fused")
        sets = batches[0].sets
        assert sets is not None and all(b.sets is sets for b in batches) and len(sets) == 3
        assert sets.kind == "fused" and (sets.by_gaussian is not None) == (device == "cuda")
        if not gathered:
            sets.by_gaussian = None
        sets.restart()
        for step in range(4):  # the fourth wraps to the first set
            b = batches[step % 3]
            Cg = C.clone().requires_grad_(True)
            loss = b.loss(Cg)
            (grad,) = torch.autograd.grad(loss, Cg)
            pix = b.pixels.cpu()
            img = A[pix] @ C.double().cpu() + contrib.transmittance[pix, None].double().cpu() * bg.double().cpu()
            err = img - target[pix].double().cpu()
            w = (torch.full((len(pix),), 1.0 / len(pix), dtype=torch.float64) if not weighted
                 else b.weight.double().cpu())
            assert weighted == (b.weight is not None)
            ref_loss = (err.abs().mean(-1) * w).sum()
            ref_grad = A[pix].T @ (w[:, None] / 3.0 * torch.sign(err))
            assert float(loss.detach()) == pytest.approx(float(ref_loss), rel=2e-6)
            assert rel_err(grad.cpu(), ref_grad) < 2e-6
        assert int(sets.counter) == 4
    assert bool((grad.cpu()[cols.bincount(minlength=U) == 0] == 0).all())


@pytest.mark.gpu
def test_the_gathered_gradient_over_long_and_short_runs_of_one_gaussian():
    """The gathered gradient (GPU) where one Gaussian is in every pixel (a run of thousands of entries
    over many warps' chunks), a few in many and most in few, over sets whose entries start anywhere
    in a chunk: the kernels' loss and gradient equal a float64 dense computation, and the scattered
    kernel's (the sets without their sorted entries)."""
    P, U = 5000, 400
    g = torch.Generator().manual_seed(11)
    per_row = [torch.cat([torch.tensor([0]), torch.randperm(U - 1, generator=g)[: int(k)] + 1])
               for k in torch.randint(0, 12, (P,), generator=g)]
    cols = torch.cat(per_row)
    rows = torch.repeat_interleave(torch.arange(P), torch.tensor([len(c) for c in per_row]))
    vals = torch.rand(rows.numel(), generator=g) * 0.5
    dev = torch.device("cuda")
    contrib = SimpleNamespace(num_pixels=P, pair_gaussian=torch.arange(U), pixel=rows.to(dev), pair=cols.to(dev),
                              weight=vals.to(dev), transmittance=torch.rand(P, generator=g).to(dev))
    target, bg = torch.rand(P, 3, generator=g).to(dev), torch.tensor([0.3, 0.1, 0.7], device=dev)
    changed = (torch.rand(P, generator=g) < 0.3).to(dev)
    C = torch.rand(U, 3, generator=g).to(dev)
    A = dense(rows, cols, vals, P, U)
    grads = {}
    for kind in ("gathered", "scattered"):
        batches = pixel_batches(contrib, target, bg, 5, 3, changed, 0.5, composite="fused")
        if kind == "scattered":
            batches[0].sets.by_gaussian = None
        batches[0].sets.restart()
        grads[kind] = []
        for b in batches:
            loss, grad = b.sets.loss_and_grad(C)
            pix = b.pixels.cpu()
            img = A[pix] @ C.double().cpu() + contrib.transmittance[pix, None].double().cpu() * bg.double().cpu()
            err = img - target[pix].double().cpu()
            w = b.weight.double().cpu()
            assert float(loss) == pytest.approx(float((err.abs().mean(-1) * w).sum()), rel=2e-6)
            assert rel_err(grad.cpu(), A[pix].T @ (w[:, None] / 3.0 * torch.sign(err))) < 2e-6
            grads[kind].append(grad)
    for a, b in zip(grads["gathered"], grads["scattered"]):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)


def test_the_gathered_kind_scatters_where_its_sorted_entries_cannot_be_built(monkeypatch):
    """Where the entries sorted by Gaussian cannot be built (out of GPU memory), the fused kind warns once
    and its steps scatter the gradient (no sorted entries); where they can, it keeps them."""
    from virgi_ns.edit.pixels import FusedSets
    from virgi_ns.raster import cuda

    P, U = 120, 60
    rows, cols, vals = random_entries(P, U, seed=8)
    contrib = SimpleNamespace(num_pixels=P, pair_gaussian=torch.arange(U), pixel=rows, pair=cols, weight=vals,
                              transmittance=torch.rand(P))
    target, bg = torch.rand(P, 3), torch.tensor([0.1, 0.5, 0.9])
    monkeypatch.setattr(FusedSets, "_use_kernel", lambda self, on: True)  # as on a GPU with our kernels
    built = []
    monkeypatch.setattr(cuda, "edit_by_gaussian", lambda *a: built.append(a) or ["sorted"])
    assert pixel_batches(contrib, target, bg, 3, 1, composite="fused")[0].sets.by_gaussian == ["sorted"]
    assert len(built) == 1 and built[0][-1] == U

    def out_of_memory(*a):
        raise torch.cuda.OutOfMemoryError("CUDA out of memory")

    monkeypatch.setattr(cuda, "edit_by_gaussian", out_of_memory)
    with pytest.warns(UserWarning, match="scatter their gradient.*free GPU memory"):
        sets = pixel_batches(contrib, target, bg, 3, 1, composite="fused")[0].sets
    assert sets.kind == "fused" and sets.by_gaussian is None


def test_fused_sets_render_the_same_pixels_as_csr():
    """A ``fused`` batch renders its pixels as a csr batch does, and its sets are csr's sets."""
    P, U = 200, 120
    rows, cols, vals = random_entries(P, U, seed=6)
    contrib = SimpleNamespace(num_pixels=P, pair_gaussian=torch.arange(U), pixel=rows, pair=cols, weight=vals,
                              transmittance=torch.rand(P))
    target, bg = torch.rand(P, 3), torch.tensor([0.1, 0.5, 0.9])
    C = torch.rand(U, 3)
    for n in (1, 4):
        ref = pixel_batches(contrib, target, bg, n, 2)
        got = pixel_batches(contrib, target, bg, n, 2, composite="fused")
        for a, b in zip(ref, got):
            if a.pixels is not None:
                assert torch.equal(a.pixels, b.pixels)
            torch.testing.assert_close(b.render(C), a.render(C), rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(b.background, a.background, rtol=0, atol=0)
            torch.testing.assert_close(b.target, a.target, rtol=0, atol=0)


def test_composite_names_are_checked():
    for bad in ("cusparse", "segment", "", "fused/csr", "fused_atomics"):
        with pytest.raises(ValueError, match="batch_composite"):
            EditConfig(batch_composite=bad)  # type: ignore[arg-type]
    cfg = EditConfig()
    with pytest.raises(ValueError, match="batch_composite must be one of auto, csr, fused"):
        cfg.batch_composite = "nope"  # type: ignore[assignment]
    assert cfg.batch_composite == "auto"  # a refused value is not kept


@pytest.mark.parametrize("n_batches", [1, 3])
def test_pixel_batches_of_both_kinds_agree(n_batches):
    """:func:`pixel_batches` cuts the same pixel sets whatever the kind; each batch's render and
    gradient equal the CSR's."""
    P, U = 300, 150
    rows, cols, vals = random_entries(P, U, seed=4)
    contrib = SimpleNamespace(num_pixels=P, pair_gaussian=torch.arange(U), pixel=rows, pair=cols, weight=vals,
                              transmittance=torch.rand(P))
    g = torch.Generator().manual_seed(2)
    target, bg = torch.rand(P, 3, generator=g), torch.tensor([0.2, 0.3, 0.4])
    changed = torch.rand(P, generator=g) < 0.2
    ref = pixel_batches(contrib, target, bg, n_batches, 7, changed, 0.5)
    C = torch.rand(U, 3, generator=g, requires_grad=True)
    for kind in ("fused",):
        got = pixel_batches(contrib, target, bg, n_batches, 7, changed, 0.5, composite=kind)
        assert len(got) == len(ref)
        for a, b in zip(ref, got):
            assert b.composite == kind and a.composite == "csr"
            torch.testing.assert_close(b.target, a.target, rtol=0, atol=0)
            torch.testing.assert_close(b.weight, a.weight, rtol=0, atol=0)
            ra, rb = a.render(C), b.render(C)
            torch.testing.assert_close(rb, ra, rtol=1e-5, atol=1e-6)
            w = torch.randn(ra.shape, generator=g)
            (ga,) = torch.autograd.grad((ra * w).sum(), C)
            (gb,) = torch.autograd.grad((rb * w).sum(), C)
            torch.testing.assert_close(gb, ga, rtol=1e-5, atol=1e-6)
    # the fused kind sizes its sets on the host; a caller's count of the changed pixels cuts the same sets
    counted = pixel_batches(contrib, target, bg, n_batches, 7, changed, 0.5, "fused", n_changed=int(changed.sum()))
    for a, b in zip(ref, counted):
        assert torch.equal(a.pixels if a.pixels is not None else torch.arange(P), b.pixels)
        assert torch.equal(a.target, b.target) and torch.equal(a.weight, b.weight)
    with pytest.raises(ValueError, match="composite"):
        pixel_batches(contrib, target, bg, n_batches, 7, composite="dense")


@pytest.fixture(scope="module")
def tiny():
    with es.one_thread():
        S = es.build(per_object=150, fit_steps=40)
        cam = S.cameras.index(0)
        before = render_view(S.scene, S.cameras, 0)["rgb"]
        edited, _ = recolor(before, RecolorRule(h0=190, h1=260, shift=135, s_min=0.3, v_min=0.1))
        # noise keeps every pixel off its target: at a zero residual the L1 gradient's sign is float
        # rounding, and Adam would turn the kinds' different summation orders into different steps
        noise = torch.rand(edited.shape, generator=torch.Generator().manual_seed(0)) - 0.5
        yield S, cam, (edited + 0.05 * noise).clamp(0.0, 1.0)


def _fit(tiny, kind: str, **kw):
    S, cam, edited = tiny
    with es.one_thread():
        eng = EditEngine(S.scene, cam, edited, cfg=EditConfig(steps=8, batch_composite=kind, whole_image=True, **kw))
        edit, timing = eng.fit()
        return eng, edit, timing


@pytest.mark.parametrize("kind", KINDS[1:])
def test_edit_with_every_kind_matches_csr(tiny, kind):
    """A few Adam steps with the fused kind give the edit CSR gives (float rounding apart)."""
    _, ref, t_ref = _fit(tiny, "csr")
    eng, got, t_got = _fit(tiny, kind)
    assert all(b.composite == kind for b in eng.batches)
    assert t_got.final_loss == pytest.approx(t_ref.final_loss, rel=1e-4)
    torch.testing.assert_close(got.head_weight, ref.head_weight, rtol=0, atol=1e-4)
    torch.testing.assert_close(got.head_bias, ref.head_bias, rtol=0, atol=1e-4)
    for (name, a), b in zip(ref.seg.state_dict().items(), got.seg.state_dict().values()):
        torch.testing.assert_close(b, a, rtol=0, atol=1e-4, msg=name)
    # and the fit moved the heads: the comparison is not between two untouched starts
    assert float((ref.head_bias - tiny[0].scene.field.diffuse_head.bias.float()).abs().max()) > 1e-3


def test_retarget_rebuilds_batches_for_another_kind(tiny):
    """A warm retarget keeps its batches only when the kind is still the same."""
    S, cam, edited = tiny
    with es.one_thread():
        eng = EditEngine(S.scene, cam, edited, cfg=EditConfig(steps=2))
        eng.fit()
        eng.cfg.batch_composite = "fused"
        eng.retarget(edited)
        assert all(b.composite == "fused" for b in eng.batches)
        eng.fit()


def test_a_warm_retarget_writes_its_own_targets_not_the_callers_image(tiny):
    """A whole-image fit in one pixel set keeps a copy of the edited image as its target, so a warm
    retarget (which writes targets in place) leaves the image the caller passed untouched."""
    S, cam, edited = tiny
    kept = edited.clone()
    with es.one_thread():
        eng = EditEngine(S.scene, cam, edited, cfg=EditConfig(steps=2, whole_image=True, pixel_batches=1))
        eng.fit()
        target = eng.batches[0].target
        eng.retarget(edited.flip(0).contiguous())
    assert eng.batches[0].target is target
    torch.testing.assert_close(target, edited.flip(0).reshape(-1, 3), atol=0, rtol=0)
    torch.testing.assert_close(edited, kept, atol=0, rtol=0)


def _gpu_scene(scene):
    """A copy of ``scene`` on the GPU, rasterized by the CUDA backend where it builds."""
    import copy

    from virgi_ns.edit.scene import FrozenScene

    return FrozenScene(scene.means.cuda(), scene.quats.cuda(), scene.scales.cuda(), scene.opacities.cuda(),
                       copy.deepcopy(scene.field).cuda(), scene.background.cuda(), backend="auto")


@pytest.mark.gpu
def test_recorded_steps_are_replayed_after_a_warm_retarget(tiny):
    """A warm retarget keeps the recorded steps, and replaying them fits the new target as eager steps
    after the same warm retarget do."""
    S, cam, edited = tiny
    gpu = _gpu_scene(S.scene)
    other = edited.flip(1).contiguous().cuda()
    fits = {}
    for graphs in (True, False):
        eng = EditEngine(gpu, cam, edited.cuda(), cfg=EditConfig(steps=20, whole_image=True, cuda_graphs=graphs))
        eng.fit()
        recorded = eng._graphs.graphs if graphs else None
        eng.retarget(other)
        fits[graphs] = eng.fit()
        assert (eng._graphs.graphs is recorded) if graphs else eng._graphs is None
    (e_g, t_g), (e_e, t_e) = fits[True], fits[False]
    torch.testing.assert_close(e_g.head_weight, e_e.head_weight, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(e_g.head_bias, e_e.head_bias, atol=1e-4, rtol=1e-4)
    assert t_g.final_loss == pytest.approx(t_e.final_loss, rel=1e-4)


@pytest.mark.gpu
@pytest.mark.parametrize("kind", KINDS)
def test_every_kind_records_as_cuda_graphs(tiny, kind):
    """On a GPU each kind's steps record as CUDA graphs (no host sync, no fallback warning) and give
    the eager steps' edit."""
    import warnings

    S, cam, edited = tiny
    gpu = _gpu_scene(S.scene)
    fits = {}
    for graphs in (True, False):
        cfg = EditConfig(steps=20, cuda_graphs=graphs, batch_composite=kind, whole_image=True)
        with warnings.catch_warnings():
            warnings.filterwarnings("error", message=".*CUDA graphs.*")
            fits[graphs] = EditEngine(gpu, cam, edited.cuda(), cfg=cfg).fit()
        assert cfg.cuda_graphs == graphs
    (e_g, t_g), (e_e, t_e) = fits[True], fits[False]
    torch.testing.assert_close(e_g.head_bias, e_e.head_bias, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(e_g.head_weight, e_e.head_weight, atol=1e-4, rtol=1e-4)
    assert t_g.final_loss == pytest.approx(t_e.final_loss, rel=1e-4)


@pytest.mark.gpu
def test_the_fused_kernel_fits_as_csr_does_on_a_gpu(tiny):
    """The fused kind's CUDA kernel (graphed) fits the edit csr fits on the same GPU, and so does a warm
    re-fit of a new target: the counter starts each fit at the first pixel set."""
    S, cam, edited = tiny
    gpu = _gpu_scene(S.scene)
    other = edited.flip(1).contiguous().cuda()
    fits = {}
    for kind in ("csr", "fused"):
        eng = EditEngine(gpu, cam, edited.cuda(), cfg=EditConfig(steps=20, batch_composite=kind, whole_image=True))
        first = eng.fit()
        eng.retarget(other)
        fits[kind] = (first, eng.fit())
    for (ref, ref_t), (got, got_t) in zip(fits["csr"], fits["fused"]):
        torch.testing.assert_close(got.head_weight, ref.head_weight, atol=1e-4, rtol=1e-4)
        torch.testing.assert_close(got.head_bias, ref.head_bias, atol=1e-4, rtol=1e-4)
        assert got_t.final_loss == pytest.approx(ref_t.final_loss, rel=1e-4)


def test_auto_is_csr_on_a_cpu_and_the_fused_kind_on_a_gpu(monkeypatch):
    from virgi_ns.edit.pixels import AUTO_GPU, resolve_composite
    from virgi_ns.raster import cuda

    assert resolve_composite("auto", torch.device("cpu")) == "csr"
    # the fused kernel where our extension runs; csr on a GPU without it
    monkeypatch.setattr(cuda, "available", lambda: (True, ""))
    assert resolve_composite("auto", torch.device("cuda")) == AUTO_GPU == "fused"
    monkeypatch.setattr(cuda, "available", lambda: (False, "nvcc not found"))
    assert resolve_composite("auto", torch.device("cuda")) == "csr"
    assert resolve_composite("auto", torch.device("cpu")) == "csr"
    assert resolve_composite("csr", torch.device("cuda")) == "csr"
    assert EditConfig().batch_composite == "auto"
