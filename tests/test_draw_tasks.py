from collections import Counter

import numpy as np
import pytest

from bpp.benchmarks.draw.demonstrator import DemoConfig, demonstrate, replay_paths
from bpp.benchmarks.draw.env import DrawEnv
from bpp.drawing.geometry import canvas_to_upright, unit_to_canvas
from bpp.drawing.human import HUMAN_GLYPHS, human_drawings
from bpp.drawing.metric import chamfer_distance, ink_mask
from bpp.drawing.procedural import ProceduralConfig, generate_drawing


def test_procedural_drawings_respect_their_config():
    rng = np.random.default_rng(0)
    kinds_seen = Counter()
    for lo, hi in [(1, 3), (4, 6), (1, 6)]:
        cfg = ProceduralConfig(min_parts=lo, max_parts=hi)
        counts = set()
        for i in range(150):
            drawing, kinds = generate_drawing(rng, cfg, f"t{i}")
            counts.add(len(kinds))
            kinds_seen.update(kinds)
            assert lo <= len(kinds) <= hi
            assert kinds[0] != "move"
            assert all(not (a == b == "move") for a, b in zip(kinds, kinds[1:], strict=False))
            for s in drawing.strokes:
                assert s.min() >= 0.0 and s.max() <= 1.0 and len(s) >= 2
            assert len(drawing.strokes) <= 1 + kinds.count("move")
        assert counts == set(range(lo, hi + 1))
    assert set(kinds_seen) == {"line", "curve", "oval", "move"}


def test_procedural_generation_is_seeded():
    a, ka = generate_drawing(np.random.default_rng(7), ProceduralConfig(), "x")
    b, kb = generate_drawing(np.random.default_rng(7), ProceduralConfig(), "x")
    assert ka == kb and all(np.array_equal(p, q) for p, q in zip(a.strokes, b.strokes, strict=True))


def test_parts_connect_back_to_earlier_endpoints():
    rng = np.random.default_rng(1)
    closed = 0
    for i in range(100):
        drawing, _ = generate_drawing(rng, ProceduralConfig(min_parts=3, max_parts=3, connect_prob=1.0), f"t{i}")
        ends = np.concatenate([[s[0], s[-1]] for s in drawing.strokes])
        # With connect_prob=1 every non-oval part ends on an earlier endpoint: some point repeats.
        d = np.linalg.norm(ends[:, None] - ends[None], axis=-1) + np.eye(len(ends))
        interior = np.concatenate(drawing.strokes)
        closed += bool((d < 1e-9).any()) or len(interior) > len(np.unique(interior.round(9), axis=0))
    assert closed > 60


@pytest.mark.parametrize("glyph", [0, 13, 38])
def test_demonstrations_reproduce_the_drawing(glyph):
    drawing = human_drawings()[glyph]
    rng = np.random.default_rng(glyph)
    target = ink_mask([unit_to_canvas(s, 0.0) for s in drawing.strokes])
    for angle in (-0.7, 0.0, 0.5):
        demo = demonstrate(drawing, angle, rng.uniform(50, 450, 2), rng)
        ink = ink_mask([canvas_to_upright(p, angle) for p in replay_paths(demo.states, demo.actions)])
        # A careful hand: the ink stays within a pixel or two of the ideal strokes (a 10 px offset scores ~9).
        assert chamfer_distance(target, ink) < 3.0
        assert len(demo) <= DemoConfig().max_steps
        assert demo.actions[-1, 2] == 0.0  # ends with the pen lifted


def test_demonstrations_vary_in_speed_and_noise():
    drawing = human_drawings()[0]
    lengths = {len(demonstrate(drawing, 0.0, np.array([100.0, 100.0]), np.random.default_rng(s))) for s in range(6)}
    assert len(lengths) >= 4


def test_recorded_demo_is_what_the_env_does():
    drawing = human_drawings()[5]
    demo = demonstrate(drawing, 0.3, np.array([400.0, 80.0]), np.random.default_rng(0))
    env = DrawEnv(image_size=None, early_stop=False)
    env.reset(options={"board_angle": 0.3, "cursor": demo.states[0, :2]})
    for state, action in zip(demo.states, demo.actions, strict=True):
        np.testing.assert_array_equal(env.state, state)
        env.step(action)
    assert len(env.paths) == len(replay_paths(demo.states, demo.actions))


def test_human_set_is_fifty_distinct_glyph_drawings():
    drawings = human_drawings()
    assert len(drawings) == len(HUMAN_GLYPHS) >= 50
    assert len({d.id for d in drawings}) == len(drawings)
    for d in drawings:
        pts = np.concatenate(d.strokes)
        assert pts.min() >= 0.0 and pts.max() <= 1.0
        assert 0.75 <= (pts.max(0) - pts.min(0)).max() <= 0.77  # normalised to span [0.12, 0.88]
