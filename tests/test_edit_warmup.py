"""The first-edit warm-up (virgi_ns.edit.warmup): it edits a made-up scene without touching the global
random state, starts only on a GPU, and a failure is kept, never raised."""

from __future__ import annotations

import torch

from virgi_ns.edit import warmup


def test_a_warm_up_edit_runs_and_leaves_the_global_random_state_alone():
    torch.manual_seed(5)
    state = torch.get_rng_state()
    seconds = warmup.warm_up("cpu", gaussians=1500, width=32, height=24)
    assert seconds > 0
    assert torch.equal(torch.get_rng_state(), state)


def test_no_warm_up_on_a_cpu_and_a_failed_one_is_kept_not_raised(monkeypatch):
    assert warmup.start("cpu") is False
    warmup.wait()  # nothing started: returns at once

    def broken(device):
        raise RuntimeError("no GPU after all")

    monkeypatch.setattr(warmup, "warm_up", broken)
    warmup._run(torch.device("cuda"))
    assert warmup.last_error == "RuntimeError: no GPU after all"
    monkeypatch.setattr(warmup, "warm_up", lambda device: 0.25)
    warmup._run(torch.device("cuda"))
    assert warmup.last_error is None and warmup.last_seconds == 0.25
