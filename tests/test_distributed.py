"""Training on several processes, on a CPU: two gloo processes (torch.multiprocessing, as
nerfstudio's launcher starts them on GPUs) against one process, on the procedural capture."""

from __future__ import annotations

import math
import os

import pytest
import torch

from method_configs.virgi import virgi_trainer_config
from virgi_ns.errors import InputError
from virgi_ns.nerfstudio import distributed
from virgi_ns.nerfstudio.datamanager import views_of_process
from virgi_ns.nerfstudio.trainer import AdamConfig, for_processes
from virgi_ns.raster import Request

from distributed_run import (cases, densify, state_of, tiny_config, train, trainer_config, trainer_worker, view_info,
                             worker)
from virgi_scene import make_scene

# Two processes with half the batch each against one with all of it: the same arithmetic but for
# the order of float32 sums (each process sums its own pixels' and views' gradients, then the two
# sums are added), which moves gradients by rounding noise (about 1e-10 here, on the quaternions of
# the isotropic Gaussians, whose exact gradient is 0). Compared with Adam's eps at 1e-6 (see
# distributed_run.EXACT_EPS), Adam's step moves by at most lr / eps times that: about 1e-7 a step,
# so 1e-5 over six steps. One process on 1 and on 2 threads differs by about 1e-6 as well.
ATOL = 1e-5


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("virgi_scene"))


@pytest.fixture(scope="module")
def two_processes(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("processes")
    distributed.run_processes(worker, 2, scene.root, scene.ply, out)
    return [torch.load(out / f"rank{r}.pt", weights_only=False) for r in range(2)]


@pytest.fixture(scope="module")
def one_process(scene):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as each of the two processes
    try:
        runs = cases(scene.ply)
        return {name: train(tiny_config(scene.root, **runs[name])) for name in ("keep", "singleview_keep")}
    finally:
        torch.set_num_threads(threads)


def _max_diff(a: dict, b: dict) -> float:
    assert a.keys() == b.keys()
    return max(float((a[k] - b[k]).abs().max()) if a[k].numel() else 0.0 for k in a)


@pytest.mark.parametrize("case", ["keep", "scale", "singleview_keep"])
def test_processes_hold_bit_identical_parameters_after_every_step(two_processes, case):
    r0, r1 = two_processes[0][case], two_processes[1][case]
    assert len(r0["agreed"]) == r0["steps"] and all(r0["agreed"]) and all(r1["agreed"])
    for a, b in zip(r0["states"], r1["states"]):
        assert all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("case", ["keep", "singleview_keep"])
def test_two_processes_with_half_the_batch_match_one_with_all_of_it(two_processes, one_process, case):
    """'keep': each process takes half of the one-process batch (one of the two views of a
    geometry step, the tiles of half the views of a colour step; in single-view mode all tiles
    fall to one process and the other steps with nothing)."""
    one, two = one_process[case], two_processes[0][case]
    assert len(one["states"]) == len(two["states"]) == one["steps"]
    diffs = [_max_diff(a, b) for a, b in zip(one["states"], two["states"])]
    print(f"{case}: max |one process - two| per step: {['%.1e' % d for d in diffs]}")
    assert max(diffs) <= ATOL, diffs
    # the gradients stepped with (Adam's step would hide a wrong scale of them): the same up to
    # rounding, relative to each tensor's largest, or to the step's largest where a tensor's exact
    # gradient is 0 (the quaternions: rounding noise only)
    for step, (a, b) in enumerate(zip(one["grads"], two["grads"])):
        assert a.keys() == b.keys() and a, step
        largest = max(float(g.abs().max()) for g in a.values())
        for k in a:
            err = float((a[k] - b[k]).abs().max())
            assert err <= 1e-4 * float(a[k].abs().max()) + 1e-6 * largest, (step, k, err)
    # the comparison is not of runs that stood still: both stages moved the parameters
    first, last = one["states"][0], one["states"][-1]
    assert _max_diff(first, last) > 1e-3 and one["frozen"] and two["frozen"]
    # and the colour batches were shared out by view
    v0, v1 = two_processes[0][case]["views"], two_processes[1][case]["views"]
    for whole, a, b in zip(one["views"], v0, v1):
        assert sorted(whole) == sorted(a + b) and not set(a) & set(b)


def test_scale_gives_each_process_a_one_process_batch_of_its_own(two_processes):
    r0, r1 = two_processes[0]["scale"], two_processes[1]["scale"]
    assert r0["steps"] == 4  # (4 geometry + 4 colour steps) / 2
    assert r0["pixel_budget"] == 2 * 5 * 256 * 2  # the batch of both; each draws half of it
    assert r0["views"] != r1["views"]  # own tiles (and own cameras: a shared order, each its own views)


def test_densification_decides_from_the_statistics_of_every_process(two_processes):
    """Constructed rasterizer outputs (the CPU geometry stage has no densification): two processes
    each seeing one view per step end with the same Gaussians as one process seeing both views."""
    from virgi_ns.nerfstudio.distributed import ReducedDefaultStrategy

    r0, r1 = two_processes[0]["densified"], two_processes[1]["densified"]
    assert r0["agreed"] and r1["agreed"]
    # one process, both views a step, gradients of their mean loss (half of each view's own)
    params, moments = densify(ReducedDefaultStrategy, [[view_info(0, s, 0.5), view_info(1, s, 0.5)] for s in (1, 2)])
    n = params["means"].shape[0]
    assert n != 64  # some Gaussians grew or were pruned
    for k in params:
        assert torch.equal(params[k], r0["params"][k]), k
        assert torch.equal(moments[k], r0["moments"][k]), k
    # each process's statistics alone would have grown other Gaussians
    grows = []
    for p in (0, 1):
        infos = [view_info(p, s) for s in (1, 2)]
        g = sum(((i["means2d"].absgrad[0] * 50).norm(dim=-1) * (i["radii"][0] > 0)) for i in infos)
        c = sum((i["radii"][0] > 0).float() for i in infos)
        grows.append(g / c.clamp_min(1) > 0.0008)
    assert not torch.equal(grows[0], grows[1])


# ------------------------------------------------------------------ without processes
def test_views_of_process_split_a_batch_by_view():
    req = Request.tiles(torch.tensor([3, 1, 3, 5, 1, 7, 3]), torch.arange(7) * 16, 0, 16)
    a, b = views_of_process(req, 0, 2), views_of_process(req, 1, 2)
    assert sorted(a.views.tolist() + b.views.tolist()) == sorted(req.views.tolist())
    assert set(a.views.tolist()) == {1, 5} and set(b.views.tolist()) == {3, 7}
    assert a.x0.tolist() == [16, 48, 64]  # the tiles keep their places


def test_scale_batch_rule():
    cfg = virgi_trainer_config("virgi", geometry_steps=7000, colour_steps=1001)
    cfg.steps_per_save = 2000
    scaled = for_processes(cfg, 4)
    m, m0 = scaled.pipeline.model, cfg.pipeline.model
    assert scaled.max_num_iterations == 1750 + 251 and m.geometry_steps == 1750
    assert (m.refine_every, m.warmup_length, m.stop_split_at, m.sh_degree_interval) == (25, 125, 3750, 250)
    assert m.geometry_views_per_step == 4 and scaled.pipeline.datamanager.pixel_budget == 4 * 163840
    assert scaled.steps_per_save == 500 and scaled.viewer.quit_on_train_completion
    means = scaled.optimizers["means"]
    assert isinstance(means["optimizer"], AdamConfig)
    assert math.isclose(means["optimizer"].lr, 2 * 1.6e-4) and math.isclose(means["optimizer"].eps, 1e-15 / 2)
    assert means["optimizer"].betas == pytest.approx((0.6, 0.996))
    assert means["scheduler"].max_steps == 1750 and math.isclose(means["scheduler"].lr_final, 2 * 1.6e-6)
    # the recipe asked for is left alone; 'keep' changes nothing but the end of the run
    assert m0.geometry_steps == 7000 and cfg.optimizers["means"]["optimizer"].lr == 1.6e-4
    cfg.pipeline.multi_gpu_batch = "keep"
    cfg.pipeline.model.geometry_views_per_step = 4
    kept = for_processes(cfg, 4)
    assert kept.max_num_iterations == cfg.max_num_iterations and kept.pipeline.model.geometry_views_per_step == 4
    assert kept.optimizers["means"]["optimizer"].lr == 1.6e-4 and kept.viewer.quit_on_train_completion
    # imported geometry: the colour stage alone is shortened
    cfg = virgi_trainer_config("virgi", geometry_steps=0, colour_steps=1000)
    cfg.pipeline.model.geometry_from = "scene.ply"
    assert for_processes(cfg, 2).max_num_iterations == 500


def test_keep_refuses_views_it_cannot_split(scene):
    cfg = tiny_config(scene.root, "keep", views=3)
    with pytest.raises(InputError, match="multiple of 2"):
        for_processes(cfg, 2)
    assert for_processes(cfg, 3).pipeline.model.geometry_views_per_step == 3
    cfg.pipeline.model.geometry_from = scene.ply  # no geometry stage: nothing to split
    for_processes(cfg, 2)


def test_one_process_trains_with_nerfstudios_pieces(scene):
    """Without a process group nothing changes: nerfstudio's optimizers, gsplat's own strategy."""
    from gsplat.strategy import DefaultStrategy
    from nerfstudio.engine.optimizers import Optimizers

    from virgi_ns.nerfstudio.pipeline import training_state

    cfg = tiny_config(scene.root, views=1)
    pipeline = cfg.pipeline.setup(device="cpu", test_mode="val")
    optimizers, _ = training_state(cfg, pipeline)
    assert type(optimizers) is Optimizers and type(pipeline.model.strategy) is DefaultStrategy
    assert pipeline.model.strategy.verbose and pipeline.world_size == 1


def test_virgi_trainer_on_two_processes(scene, tmp_path):
    """nerfstudio's trainer loop through virgi's trainer: the batch rule, averaged gradients, one
    checkpoint and one log (rank 0's), and a checkpoint that loads in one process."""
    distributed.run_processes(trainer_worker, 2, scene.root, tmp_path)
    r0, r1 = (torch.load(tmp_path / f"trainer_rank{r}.pt", weights_only=False) for r in range(2))
    assert r0["agreed"] and r1["agreed"] and r0["optimizers"] == "DistributedOptimizers"
    assert r0["steps"] == 4  # (4 + 4) / 2
    if not os.environ.get("OMP_NUM_THREADS"):  # each process its half of the host's threads
        assert r0["threads"] == r1["threads"] == max(1, r0["host_threads"] // 2)
    run = tmp_path / "tiny" / "virgi-test" / "run"
    ckpts = list((run / "nerfstudio_models").glob("*.ckpt"))
    assert [c.name for c in ckpts] == ["step-000000003.ckpt"]
    assert len(list(run.rglob("events.out.tfevents.*"))) == 1
    # the checkpoint keeps the one-process layout: a one-process pipeline loads it as it is
    cfg = trainer_config(scene.root, tmp_path)
    pipeline = cfg.pipeline.setup(device="cpu", test_mode="val")
    loaded = torch.load(ckpts[0], map_location="cpu", weights_only=False)
    pipeline.load_pipeline(loaded["pipeline"], loaded["step"])
    state = state_of(pipeline.model)
    assert all(torch.equal(state[k], r0["state"][k]) for k in state) and pipeline.model.geometry_frozen


def test_each_process_takes_its_share_of_the_cpu_threads(monkeypatch):
    """Processes sized for the whole host wait on each other's threads (the colour stage's batch
    drawing slowed 10x on two GPUs): each takes the host's threads over the processes on it, and a
    user's OMP_NUM_THREADS stands. (The two-process trainer test checks it through the trainer.)"""
    before = torch.get_num_threads()
    host = distributed.host_threads()
    try:
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
        assert distributed.processes_per_host(3) == 3  # no process group: all on this host
        for world, want in ((1, host), (2, max(1, host // 2)), (4 * host, 1)):
            torch.set_num_threads(host)  # each call starts from the whole host
            assert distributed.share_cpu_threads(world) == want == torch.get_num_threads()
        torch.set_num_threads(host)
        assert distributed.share_cpu_threads(2) == max(1, host // 2)  # again: not halved twice
        # a process driving a GPU keeps at most GPU_PROCESS_THREADS, alone or sharing the host
        monkeypatch.setattr(distributed, "GPU_PROCESS_THREADS", 1)
        for world in (1, 2):
            torch.set_num_threads(host)
            assert distributed.share_cpu_threads(world, "cuda") == 1 == torch.get_num_threads()
        monkeypatch.setattr(distributed, "GPU_PROCESS_THREADS", 4 * host)
        torch.set_num_threads(host)
        assert distributed.share_cpu_threads(1, "cuda") == host  # a bound above the host's threads changes nothing
        torch.set_num_threads(host)
        monkeypatch.setenv("OMP_NUM_THREADS", "1")
        assert distributed.share_cpu_threads(2, "cuda") == host == torch.get_num_threads()
        torch.set_num_threads(host)
        assert distributed.share_cpu_threads(2) == host == torch.get_num_threads()
    finally:
        torch.set_num_threads(before)
