"""The recovery bench's move (`pipeline.benchmarks.solve_recovery`): it keeps the moved light in
the room, judged by the scene's own ray caster, on the set, whose window light the bench's first
direction takes out of the hall."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.benchmarks.solve_recovery import MOVE, MOVE_DIRECTIONS, MOVE_MARGIN, clear_move, stays_in_room
from pipeline.scene import load_scene
from pipeline.scenes import SCENES
from pipeline.scenes import set as set_scene
from pipeline.tracing import Tracer

HALL = np.array(
    [
        (-set_scene.HALF_WIDTH, 0.0, -set_scene.HALF_LENGTH),
        (set_scene.HALF_WIDTH + set_scene.WALL, set_scene.HEIGHT, set_scene.HALF_LENGTH),
    ]
)
"""The hall's inside, and the east wall's thickness where the window light sits (cm)."""
DIAGONAL = float(np.linalg.norm(HALL[1] - HALL[0]))


@pytest.fixture(scope="module")
def tracer(tmp_path_factory: pytest.TempPathFactory) -> Tracer:
    shot = SCENES["set"].write(tmp_path_factory.mktemp("set"))
    return Tracer.for_scene(load_scene(shot))


def test_a_move_through_the_wall_or_out_of_the_room_is_refused(tracer: Tracer) -> None:
    window = np.array([set_scene.HALF_WIDTH + 0.5 * set_scene.WALL, 350.0, set_scene.WINDOW_Z[2]])
    margin = MOVE_MARGIN * DIAGONAL
    # Out through the window opening: nothing in the way (the tracer alone would take it), but
    # outside the room.
    outward = window + MOVE * DIAGONAL * np.asarray(MOVE_DIRECTIONS[0])
    assert stays_in_room(tracer, window, outward, np.array([HALL[0], outward + 1.0]), margin)
    assert not stays_in_room(tracer, window, outward, HALL, margin)
    # From inside the hall through the pier between two windows: inside the box, but occluded.
    inside = np.array([900.0, 350.0, 0.0])
    assert not stays_in_room(tracer, inside, inside + (200.0, 0.0, 0.0), np.array([HALL[0], HALL[1] + 500.0]), margin)
    assert stays_in_room(tracer, inside, inside - (200.0, 0.0, 0.0), HALL, margin)


def test_clear_move_takes_the_first_direction_that_stays_in_the_room(tracer: Tracer) -> None:
    window = np.array([set_scene.HALF_WIDTH + 0.5 * set_scene.WALL, 350.0, set_scene.WINDOW_Z[2]])
    offset = clear_move(tracer, window, HALL, DIAGONAL)
    assert np.linalg.norm(offset) == pytest.approx(MOVE * DIAGONAL)
    assert offset[0] < 0.0  # into the hall
    index = next(k for k, d in enumerate(MOVE_DIRECTIONS) if np.allclose(offset, MOVE * DIAGONAL * np.asarray(d)))
    step, margin = MOVE * DIAGONAL, MOVE_MARGIN * DIAGONAL
    for earlier in MOVE_DIRECTIONS[:index]:
        assert not stays_in_room(tracer, window, window + step * np.asarray(earlier), HALL, margin)
    with pytest.raises(RuntimeError, match="stays in the room"):
        pier = np.array([set_scene.HALF_WIDTH + 0.5 * set_scene.WALL, 350.0, 0.0])  # inside the wall, between windows
        clear_move(tracer, pier, HALL, DIAGONAL)
