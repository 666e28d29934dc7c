"""Placement sampling with keepouts and rejection sampling, as Safety-Gym's (docs/safety_envs.md).

Positions are planar (x, y) in m. Each object is drawn uniformly in the placement extents shrunk by its own
keepout; a draw is valid when its distance to every object already placed is at least the sum of the two
keepouts plus the margin. Batches of candidates are drawn at once and the first valid one is taken, which has
the same distribution as drawing one at a time.
"""

from collections.abc import Sequence

import numpy as np

Extents = tuple[float, float, float, float]


class ResamplingError(RuntimeError):
    """No valid layout (or goal position) was found within the allowed number of draws."""


def shrink(extents: Extents, keepout: float) -> Extents:
    """The extents (xmin, ymin, xmax, ymax) shrunk on every side by ``keepout``."""
    xmin, ymin, xmax, ymax = extents
    return (xmin + keepout, ymin + keepout, xmax - keepout, ymax - keepout)


def _first_valid(
    rng: np.random.Generator,
    region: Extents,
    keepout: float,
    placed_xy: np.ndarray,
    placed_keepout: np.ndarray,
    margin: float,
    draws: int,
) -> np.ndarray | None:
    """First of ``draws`` uniform candidates in ``region`` that respects every keepout, or None."""
    xmin, ymin, xmax, ymax = region
    candidates = rng.uniform((xmin, ymin), (xmax, ymax), size=(draws, 2))
    if len(placed_xy) == 0:
        return candidates[0]
    dist = np.linalg.norm(candidates[:, None, :] - placed_xy[None, :, :], axis=-1)
    valid = np.all(dist >= placed_keepout[None, :] + keepout + margin, axis=1)
    index = int(np.argmax(valid))
    return candidates[index] if valid[index] else None


def sample_layout(
    rng: np.random.Generator,
    objects: Sequence[tuple[str, float]],
    extents: Extents,
    margin: float = 0.0,
    draws_per_object: int = 100,
    max_layouts: int = 10_000,
) -> dict[str, np.ndarray]:
    """Place ``objects`` (name, keepout) in order; return {name: xy (2,)}.

    Each object gets ``draws_per_object`` draws; if one fails the whole layout is redrawn, up to
    ``max_layouts`` times, after which :class:`ResamplingError` is raised.
    """
    keepouts = np.array([keepout for _, keepout in objects], dtype=np.float64)
    for _ in range(max_layouts):
        placed = np.zeros((len(objects), 2))
        for i, (_, keepout) in enumerate(objects):
            xy = _first_valid(rng, shrink(extents, keepout), keepout, placed[:i], keepouts[:i], margin, draws_per_object)
            if xy is None:
                break
            placed[i] = xy
        else:
            return {name: placed[i] for i, (name, _) in enumerate(objects)}
    raise ResamplingError(f"Failed to find a valid layout after {max_layouts} tries")


def sample_position(
    rng: np.random.Generator,
    keepout: float,
    extents: Extents,
    others_xy: np.ndarray,
    others_keepout: np.ndarray,
    margin: float = 0.0,
    max_draws: int = 10_000,
    batch: int = 100,
) -> np.ndarray | None:
    """One position (2,) for an object with ``keepout`` against fixed others (k, 2), or None after ``max_draws``."""
    region = shrink(extents, keepout)
    for _ in range(max_draws // batch):
        xy = _first_valid(rng, region, keepout, others_xy, others_keepout, margin, batch)
        if xy is not None:
            return xy
    return None
