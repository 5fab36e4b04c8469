"""`CutsRelightSettings(compiled=True)`: the cuts' BRDF blocks (`relight_torch.cuts.blocks`) run
through `torch.compile` (inductor, C++) equal the eager functions they are compiled from, and a
failure to compile is a one-line `RelightError` naming the setting (never a silent eager run)."""

from __future__ import annotations

import os
import subprocess
import sys

import torch

from relight_torch.cuts.blocks import BlockEvaluator


def _block(generator: torch.Generator, rows: int, width: int, num_nodes: int) -> dict[str, torch.Tensor]:
    """A random block: node points (3, num_nodes) unit directions, frames (rows, 3, 4) (not quite
    orthonormal, as stored in float16, with the viewer's direction in the last column), materials."""

    def uniform(*shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=generator)

    points = torch.nn.functional.normalize(torch.randn(num_nodes, 3, generator=generator), dim=-1).t().contiguous()
    frames = torch.linalg.qr(torch.randn(rows, 3, 3, generator=generator))[0].half().float()
    wo = torch.nn.functional.normalize(torch.randn(rows, 3, generator=generator), dim=-1)
    wo[:, 2] = wo[:, 2].abs() * torch.where(uniform(rows) < 0.1, -1.0, 1.0)  # a few viewers below
    geometry = torch.cat((frames, frames @ wo.unsqueeze(-1)), dim=-1)
    return {
        "node_points": points,
        "geometry": geometry,
        "roughnesses": 0.05 + uniform(rows, 1),
        "cos_e": wo[:, 2:],
        "view_sq": (wo * wo).sum(-1, keepdim=True),
        "weight": uniform(rows, width),
    }


def test_compiled_blocks_equal_the_eager_functions(cxx_compiler):
    # One small grid block (every cluster in every row, written into a strided view as the
    # relighter's) and one dense block (entries summed into cells), compiled vs eager, float32.
    # Roughness >= 0.2: sharper lobes amplify float32 rounding (N.h near 1) and any reordering of
    # the same operations shows (roughness 0.05: 1.1e-5 of the peak, as eager float32 against float64
    # differs by 3e-5 there). Dense sums differ in summation order only.
    generator = torch.Generator().manual_seed(5)
    rows, width, num_nodes, num_cells = 37, 23, 61, 19
    block = _block(generator, rows, width, num_nodes)
    nodes = torch.randint(0, num_nodes, (width,), generator=generator)
    node = torch.randint(0, num_nodes, (rows, width), generator=generator).int()
    cells = torch.randint(0, num_cells, (rows * width,), generator=generator)
    results = []
    for compiled, dtype in ((False, torch.float64), (False, torch.float32), (True, torch.float32)):
        evaluator = BlockEvaluator(4, dtype, torch.device("cpu"), compiled)
        args = tuple(
            t.to(dtype)
            for t in (
                block["geometry"],
                block["node_points"],
                0.15 + block["roughnesses"],
                block["cos_e"],
                block["view_sq"],
                block["weight"],
            )
        )
        geometry, points, roughness, cos_e, view_sq, weight = args
        grid = torch.zeros(4, rows, width + 2, dtype=dtype)
        evaluator.grid(points, nodes, geometry, None, (roughness,), cos_e, view_sq, weight, grid[:, :, :width])
        sums = torch.zeros(4, num_cells, dtype=dtype)
        evaluator.dense(points, node, geometry, None, (roughness,), cos_e, view_sq, weight, cells, sums.view(-1), 0)
        results.append((grid.double(), sums.double()))
    exact, eager, compiled = results
    grid = eager[0]
    assert float(grid.abs().max()) > 0 and bool((grid[:, :, width:] == 0).all())
    assert bool((grid[:, :, :width] == 0).any())  # some directions below a horizon
    for factor in range(4):
        torch.testing.assert_close(
            compiled[0][factor], grid[factor], rtol=1e-5, atol=1e-6 * float(grid[factor].abs().max())
        )
        # Sums of ~45 entries, against float64: the lobe (factors 2, 3) is ill-conditioned near
        # N.h = 1 (d ln D / d N.h ~ 4 / alpha^2), so float32 dot products rounded differently
        # (eager's addcmul, compiled C++) move it by ~1e-5 of the peak (measured: eager 2.7e-6,
        # compiled 1.4e-5; the factors 0 and 1 agree to 1e-7).
        peak = float(exact[1][factor].abs().max())
        for result in (eager, compiled):
            assert float((result[1][factor] - exact[1][factor]).abs().max()) <= 3e-5 * peak


def test_a_failed_compile_names_the_setting(tmp_path):
    # No C++ compiler: a RelightError naming CutsRelightSettings(compiled=...), not an eager fallback.
    script = (
        "import torch\n"
        "from relight_torch.cuts.blocks import BlockEvaluator\n"
        "from relight_torch.errors import RelightError\n"
        "evaluator = BlockEvaluator(4, torch.float32, torch.device('cpu'), True)\n"
        "geometry = torch.eye(3).expand(2, 3, 3)\n"
        "geometry = torch.cat((geometry, geometry[:, :, 2:]), dim=-1)\n"
        "args = (torch.eye(3), torch.tensor([[0, 1], [2, 1]], dtype=torch.int32), geometry, None,\n"
        "        (torch.full((2, 1), 0.5),), torch.ones(2, 1), torch.ones(2, 1), torch.ones(2, 2),\n"
        "        torch.tensor([0, 1, 1, 0]), torch.zeros(8), 0)\n"
        "try:\n"
        "    evaluator.dense(*args)\n"
        "except RelightError as error:\n"
        "    print('ERROR', error)\n"
    )
    env = dict(
        os.environ,
        CXX=str(tmp_path / "no-such-g++"),
        TORCHINDUCTOR_CACHE_DIR=str(tmp_path / "inductor"),
        TORCHINDUCTOR_FX_GRAPH_CACHE="0",
        OMP_NUM_THREADS="1",
    )
    result = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
    lines = [line for line in result.stdout.splitlines() if line.startswith("ERROR")]
    assert len(lines) == 1, result.stdout + result.stderr
    assert "CutsRelightSettings(compiled=True)" in lines[0] and "compiled=False" in lines[0]
