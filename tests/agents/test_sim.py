"""The simulation's rendering beside torch in one process."""

import subprocess
import sys
import textwrap

import pytest

pytest.importorskip("triton", reason="triton (which torch's CUDA builds bring) is not installed")

RENDER_THEN_TORCH = textwrap.dedent("""
    from agents.world import Layout, Sim

    with Sim(Layout.from_seed(0, "TR")) as sim:
        image = sim.render("head", 24, 32)
    import torch

    torch.use_deterministic_algorithms(True)  # imports torch._inductor, which imports triton
    print("ok", int(image.sum() > 0))
""")


def test_a_world_that_rendered_lets_torch_load_triton_after():
    # in a process of its own: the failure it guards against is a SIGSEGV
    done = subprocess.run([sys.executable, "-c", RENDER_THEN_TORCH], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f"exit {done.returncode}\n{done.stderr[-2000:]}"
    assert done.stdout.split() == ["ok", "1"]
