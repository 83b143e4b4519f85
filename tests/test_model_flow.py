"""Flow matching and the Euler sampler agree on 1-D toys with known answers."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch

from egosim.model.errors import ModelConfigError
from egosim.model.flow import FlowMatching
from egosim.model.sampler import euler_sample


@pytest.fixture(autouse=True)
def _one_thread() -> Iterator[None]:
    """Tiny models run faster on one thread, above all on a shared, loaded machine."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


MU, SIGMA = 2.0, 0.5  # data distribution N(MU, SIGMA^2)


def exact_velocity(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """E[e - x0 | x_t] for x0 ~ N(MU, SIGMA^2), e ~ N(0, 1), x_t = (1-t) x0 + t e (Gaussian)."""
    t = t.view(-1, *([1] * (x.ndim - 1))).double()
    var = (1 - t) ** 2 * SIGMA**2 + t**2
    cov = t - (1 - t) * SIGMA**2  # Cov(e - x0, x_t)
    return -MU + cov / var * (x.double() - (1 - t) * MU)


# shift > 1 coarsens the grid near the data end, so it needs more Euler steps for 0.02 accuracy
@pytest.mark.parametrize(("shift", "steps"), [(1.0, 50), (3.0, 200)])
def test_euler_with_exact_field_lands_on_the_data(shift: float, steps: int) -> None:
    flow = FlowMatching(shift=shift)
    noise = torch.randn(20000, 1, generator=torch.Generator().manual_seed(0))
    x = euler_sample(exact_velocity, noise, flow, steps=steps)
    assert abs(float(x.mean()) - MU) < 0.02
    assert abs(float(x.std()) - SIGMA) < 0.02


def test_point_mass_is_reached_exactly() -> None:
    # data = point mass at 1.5: the velocity is (x - 1.5) / t, the straight line to the point
    x = euler_sample(
        lambda x, t: (x - 1.5) / t.view(-1, 1), torch.randn(100, 1), FlowMatching(), steps=50
    )
    torch.testing.assert_close(x, torch.full_like(x, 1.5))


def test_loss_is_minimised_by_the_exact_field() -> None:
    flow = FlowMatching()
    x0 = MU + SIGMA * torch.randn(50000, 1, generator=torch.Generator().manual_seed(1))
    losses = []
    for bias in (0.0, 0.2):
        g = torch.Generator().manual_seed(2)  # same (t, e) draws for both
        losses.append(float(flow.loss(lambda x, t, b=bias: exact_velocity(x, t) + b, x0, g)))
    # a constant offset b adds exactly b^2 to the expected squared error
    assert losses[1] - losses[0] == pytest.approx(0.04, abs=0.005)


def test_trained_velocity_net_samples_the_data() -> None:
    torch.manual_seed(0)
    net = torch.nn.Sequential(
        torch.nn.Linear(2, 64),
        torch.nn.SiLU(),
        torch.nn.Linear(64, 64),
        torch.nn.SiLU(),
        torch.nn.Linear(64, 1),
    )
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    flow = FlowMatching()
    g = torch.Generator().manual_seed(0)

    def v(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return net(torch.cat([x, t.view(-1, 1).to(x)], dim=1))

    for _ in range(300):
        x0 = MU + SIGMA * torch.randn(256, 1, generator=g)
        loss = flow.loss(v, x0, g)
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        x = euler_sample(v, torch.randn(4000, 1, generator=g), flow, steps=50)
    assert abs(float(x.mean()) - MU) < 0.1
    assert abs(float(x.std()) - SIGMA) < 0.1


def test_shift_and_grid() -> None:
    flow = FlowMatching(shift=3.0)
    grid = flow.sampling_times(4)
    assert float(grid[0]) == 1.0 and float(grid[-1]) == 0.0
    assert float(flow.shift_time(torch.tensor(0.5))) == pytest.approx(0.75)
    with pytest.raises(ModelConfigError, match="shift"):
        FlowMatching(shift=0.0)
