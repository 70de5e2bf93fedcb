"""Loading nerfstudio checkpoints on torch >= 2.6 without environment variables (virgi_ns.nerfstudio.compat)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from nerfstudio.engine.optimizers import AdamOptimizerConfig, Optimizers
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig

pytestmark = pytest.mark.skipif(
    not hasattr(torch.serialization, "add_safe_globals"), reason="torch without safe-loading allow-lists"
)

STEP = 7


class TinyPipeline(torch.nn.Module):
    """Stands in for a splatfacto pipeline: a few Gaussian parameter tensors."""

    def __init__(self, seed: int) -> None:
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        self.gauss_params = torch.nn.ParameterDict(
            {
                "means": torch.nn.Parameter(torch.randn(10, 3, generator=g)),
                "features_dc": torch.nn.Parameter(torch.rand(10, 3, generator=g)),
            }
        )


def _splatfacto_style_optimizers(pipe: TinyPipeline) -> Optimizers:
    """Optimizers as splatfacto's recipe builds them (numpy-computed exponential decay for ``means``)."""
    config = {
        "means": {
            "optimizer": AdamOptimizerConfig(lr=1.6e-4, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=1.6e-6, max_steps=30000),
        },
        "features_dc": {"optimizer": AdamOptimizerConfig(lr=0.0025, eps=1e-15), "scheduler": None},
    }
    groups = {name: [param] for name, param in pipe.gauss_params.items()}
    return Optimizers(config, groups)


def _save_checkpoint(ckpt_dir: Path) -> TinyPipeline:
    """Train a few steps and save the way ``Trainer.save_checkpoint`` does."""
    pipe = TinyPipeline(seed=0)
    optimizers = _splatfacto_style_optimizers(pipe)
    scaler = torch.amp.GradScaler("cpu", init_scale=1024.0)
    for step in range(STEP):
        optimizers.zero_grad_all()
        loss = sum((p**2).sum() for p in pipe.parameters())
        scaler.scale(loss).backward()
        optimizers.optimizer_scaler_step_all(scaler)
        scaler.update()
        optimizers.scheduler_step_all(step)
    # the premise of the work-around: the schedulers leave numpy scalars in the saved state
    assert isinstance(optimizers.optimizers["means"].param_groups[0]["lr"], np.float64)
    ckpt_dir.mkdir(parents=True)
    torch.save(
        {
            "step": STEP,
            "pipeline": pipe.state_dict(),
            "optimizers": {k: v.state_dict() for (k, v) in optimizers.optimizers.items()},
            "schedulers": {k: v.state_dict() for (k, v) in optimizers.schedulers.items()},
            "scalers": scaler.state_dict(),
        },
        ckpt_dir / f"step-{STEP:09d}.ckpt",
    )
    return pipe


def _run(code: str, *args: str) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter with no torch loading overrides in the environment."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("TORCH_FORCE")}
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code), *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


LOAD_LIKE_NERFSTUDIO = f"""
    import sys
    from pathlib import Path

    import numpy as np
    import torch

    assert "virgi_ns.nerfstudio.compat" not in sys.modules
    # what every ns-* command does first: discover methods and dataparsers through entry points
    from nerfstudio.configs.method_configs import all_methods

    assert "virgi_ns.nerfstudio.compat" in sys.modules  # brought in by entry-point discovery alone
    from nerfstudio.engine.trainer import Trainer, TrainerConfig
    from nerfstudio.utils.eval_utils import eval_load_checkpoint

    sys.path.insert(0, {str(Path(__file__).resolve().parent)!r})
    from test_compat import TinyPipeline, _splatfacto_style_optimizers

    assert "virgi" in all_methods, sorted(all_methods)
    ckpt_dir = Path(sys.argv[1])

    class Pipe(TinyPipeline):
        def load_pipeline(self, state, step):
            self.load_state_dict(state)
            self.loaded_step = step

    # ns-eval / ns-render / ns-viewer path
    config = TrainerConfig(load_dir=ckpt_dir)
    pipe = Pipe(seed=1)
    path, step = eval_load_checkpoint(config, pipe)
    assert step == {STEP} and pipe.loaded_step == {STEP}
    torch.save(pipe.state_dict(), ckpt_dir.parent / "eval_loaded.pt")

    # ns-train --load-dir path (pipeline, optimizers, schedulers, grad scaler)
    trainer = Trainer.__new__(Trainer)
    trainer.config = TrainerConfig(load_dir=ckpt_dir, load_scheduler=True)
    trainer.pipeline = Pipe(seed=2)
    trainer.optimizers = _splatfacto_style_optimizers(trainer.pipeline)
    trainer.grad_scaler = torch.amp.GradScaler("cpu")
    trainer._load_checkpoint()
    assert trainer._start_step == {STEP} + 1
    lr = trainer.optimizers.optimizers["means"].param_groups[0]["lr"]
    assert isinstance(lr, np.float64), type(lr)
    print("LR", repr(float(lr)), "SCALE", trainer.grad_scaler.get_scale())
"""


def test_checkpoint_loads_through_nerfstudio_without_env(tmp_path: Path) -> None:
    saved = _save_checkpoint(tmp_path / "nerfstudio_models")
    out = _run(LOAD_LIKE_NERFSTUDIO, str(tmp_path / "nerfstudio_models"))
    assert out.returncode == 0, out.stderr[-3000:]
    loaded = torch.load(tmp_path / "eval_loaded.pt")
    for name, value in saved.state_dict().items():
        assert torch.equal(loaded[name], value), name
    # the learning rate and grad-scaler scale that came back are the ones that were saved
    ckpt = torch.load(tmp_path / "nerfstudio_models" / f"step-{STEP:09d}.ckpt", weights_only=False)
    lr_line = [line for line in out.stdout.splitlines() if line.startswith("LR ")][-1].split()
    assert float(lr_line[1]) == float(ckpt["optimizers"]["means"]["param_groups"][0]["lr"])
    assert float(lr_line[3]) == ckpt["scalers"]["scale"]


def test_plain_safe_load_refuses_the_same_checkpoint(tmp_path: Path) -> None:
    """Control: without our package, torch's default load rejects the numpy scalar."""
    _save_checkpoint(tmp_path / "ckpt")
    out = _run(
        """
        import sys, torch
        try:
            torch.load(sys.argv[1], map_location="cpu")
        except Exception as err:
            print("REFUSED", type(err).__name__, "numpy" in str(err))
        """,
        str(tmp_path / "ckpt" / f"step-{STEP:09d}.ckpt"),
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert "REFUSED UnpicklingError True" in out.stdout


def test_allow_list_is_narrow(tmp_path: Path) -> None:
    """Safe loading stays on: a numpy array (or any other global) is still refused after the work-around."""
    path = tmp_path / "array.ckpt"
    torch.save({"step": 1, "array": np.arange(3)}, path)
    torch.save({"lr": np.float64(0.5) * 2}, tmp_path / "scalar.ckpt")
    out = _run(
        """
        import sys, torch
        import virgi_ns.nerfstudio.compat
        torch.load(sys.argv[1].replace("array", "scalar"), map_location="cpu")
        try:
            torch.load(sys.argv[1], map_location="cpu")
        except Exception as err:
            print("REFUSED", type(err).__name__)
        """,
        str(path),
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert "REFUSED UnpicklingError" in out.stdout


@pytest.mark.parametrize("module", ["numpy.core.multiarray", "numpy._core.multiarray"])
def test_scalar_loads_under_either_numpy_spelling(tmp_path: Path, module: str) -> None:
    """numpy 1.x pickles its scalars as numpy.core.multiarray.scalar, numpy 2.x as numpy._core...;
    a checkpoint written with either loads with either."""
    import zipfile

    import virgi_ns.nerfstudio.compat  # noqa: F401

    src, dst = tmp_path / "src.ckpt", tmp_path / "dst.ckpt"
    torch.save({"lr": np.float64(0.25) * np.exp(-1.0)}, src)
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_STORED) as zout:
        for item in zin.infolist():
            data = zin.read(item)
            if item.filename.endswith("data.pkl"):
                for spelling in (b"numpy.core.multiarray\nscalar\n", b"numpy._core.multiarray\nscalar\n"):
                    data = data.replace(spelling, module.encode() + b"\nscalar\n")
                assert module.encode() + b"\nscalar\n" in data
            zout.writestr(item, data)
    lr = torch.load(dst, map_location="cpu")["lr"]
    assert isinstance(lr, np.float64) and lr == np.float64(0.25) * np.exp(-1.0)
