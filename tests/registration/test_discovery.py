"""Discovery on an analytic room: every object found, identified and registered with no boxes;
what the library lacks stays unmatched."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from regnf.fields.analytic import Box, Cylinder, Transformed, Union
from regnf.fields.similarity import similarity_matrix
from regnf.registration.candidates import CandidateConfig
from regnf.registration.discovery import DiscoveryConfig, discover
from regnf.registration.transform import SimilarityTransform

from .fixtures import OBJECT_HI, OBJECT_LO, make_object, placement
from .test_pipeline import errors

# The test object twice (one library object, two places), and a lamp the library lacks.
PLACED = {"a": placement([0, 0, 1], 0.6, [1.0, 0.6, 0.0], 1.0),
          "b": placement([0, 0, 1], -1.9, [-1.1, -0.7, 0.0], 1.0)}
LIBRARY_FACTOR = 2.0  # the library's units: half a metre (scale is not known in advance)


@pytest.fixture(scope="module")
def result():
    floor = Box((3.0, 3.0, 0.05), (0.0, 0.0, -0.05))
    lamp = Cylinder(0.12, 0.7, (0.9, -1.4, 0.7))  # 1.4 m tall, 24 cm wide
    scene = Union(floor, lamp, *(Transformed(make_object(), M) for M in PLACED.values()), label="scene")
    lib_obj = Transformed(make_object(), np.asarray(similarity_matrix(np.eye(3), np.zeros(3), LIBRARY_FACTOR)),
                          name="testobj", label="chair")
    table = Box((0.7, 0.4, 0.37), (0.0, 0.0, 0.37), name="table", label="table")
    config = DiscoveryConfig(candidates=CandidateConfig(resolution=128), shortlist=2)
    return discover(scene, {"testobj": lib_obj, "table": table}, config)


def test_both_copies_are_found_identified_and_registered(result) -> None:
    chosen = [d for d in result.instances]
    assert sorted(d.chosen.library_name for d in chosen) == ["testobj", "testobj"]
    for name, M in PLACED.items():
        centre = M[:3, :3] @ ((OBJECT_LO + OBJECT_HI) / 2) + M[:3, 3]
        mine = [d for d in chosen if np.linalg.norm(d.candidate.box.center[:2] - centre[:2]) < 0.3]
        assert len(mine) == 1, f"copy {name}: {len(mine)} instances near it"
        assert mine[0].tried[0].library_name == "testobj"  # its short registration ranked it first
        truth = SimilarityTransform.from_matrix(
            np.asarray(similarity_matrix(np.eye(3), np.zeros(3), LIBRARY_FACTOR)) @ np.linalg.inv(M))
        r, t, s = errors(mine[0].chosen.result.transform, truth)
        assert r <= 0.02 and t <= 0.01 and s <= 0.01, f"copy {name}: {r:.4f} rad, {t:.4f}, {s:.4f}"


def test_the_lamp_the_library_lacks_stays_unmatched(result) -> None:
    assert len(result.unmatched) == 1
    lamp = result.unmatched[0]
    np.testing.assert_allclose(lamp.candidate.box.center[:2], [0.9, -1.4], atol=0.05)
    assert all(t.result is None or not t.result.accepted for t in lamp.tried)
    assert lamp.chosen is None
    assert len(result.discoveries) == 3


def test_no_library_is_an_error() -> None:
    with pytest.raises(ValueError, match="at least one library object"):
        discover(Box((1.0, 1.0, 1.0)), {})


@pytest.mark.parametrize("pillow_seen", [True, False])
def test_two_objects_that_differ_only_where_no_view_looked_are_ambiguous(pillow_seen: bool) -> None:
    import torch

    from regnf.fields.analytic import Sphere
    from regnf.observations.visibility import VisibilityGrid
    from regnf.registration.observed_difference import observed_difference
    from regnf.registration.result import RegistrationResult
    from regnf.registration.sampling import sample_surface

    M = PLACED["a"]
    pillow_at = np.array([0.2, -0.1, 0.45])  # canonical object metres, above the seat
    plain = make_object()
    with_pillow = Union(make_object(), Sphere(0.1, tuple(pillow_at)), name="pillow")
    scene = Union(Box((3.0, 3.0, 0.05), (0.0, 0.0, -0.05)), Transformed(make_object(), M), label="scene")
    lo, hi = np.array([-3.0, -3.0, -0.2]), np.array([3.0, 3.0, 2.0])
    res = np.array([60, 60, 22])  # 10 cm voxels
    counts = torch.full(tuple(res), 255, dtype=torch.uint8)
    if not pillow_seen:  # no view saw the space where the pillow would be
        centres = lo + (np.stack(np.meshgrid(*[np.arange(r) for r in res], indexing="ij"), -1) + 0.5) * (hi - lo) / res
        where = M[:3, :3] @ pillow_at + M[:3, 3]
        counts[torch.as_tensor(np.linalg.norm(centres - where, axis=-1) < 0.3)] = 0
    scene.visibility = VisibilityGrid(counts, np.stack([lo, hi]))
    truth = SimilarityTransform.from_matrix(np.linalg.inv(M))  # scene -> canonical = library frame
    results = [RegistrationResult(truth, 0.9, True, "regnf",
                                  samples=(np.zeros((1, 3)), sample_surface(f, None, side="library").points))
               for f in (plain, with_pillow)]
    seen = observed_difference(scene, plain, results[0], with_pillow, results[1])
    if pillow_seen:
        assert seen > 0.9
    else:
        assert seen < 0.05
    # The same object twice does not differ anywhere.
    assert np.isnan(observed_difference(scene, plain, results[0], plain, results[0]))


def _halves():
    """Two overlapping halves of one object, one far candidate and one that touches a half."""
    from regnf.registration.candidates import Candidates, candidate_of

    from .fixtures import make_object

    rng = np.random.default_rng(0)

    def cloud(lo: list[float], hi: list[float]) -> np.ndarray:
        return rng.uniform(lo, hi, size=(300, 3))

    field, cfg = make_object(), DiscoveryConfig()
    left, right = cloud([0.0, 0.0, 0.0], [0.5, 1.0, 0.8]), cloud([0.4, 0.0, 0.0], [1.0, 1.0, 0.8])
    far, touching = cloud([3.0, 0.0, 0.0], [3.6, 0.5, 0.8]), cloud([0.9, 0.5, 0.0], [1.5, 1.2, 0.8])
    cands = [candidate_of(p, [], field, cfg.candidates) for p in (left, right, far, touching)]
    return field, cfg, Candidates(cands, [], 1200), np.vstack([left, right])


def each(examine):
    """``examined``'s batch examiner from a one-candidate one."""
    def examine_all(cands, on_done):
        out = []
        for c in cands:
            out.append(examine(c))
            on_done()
        return out
    return examine_all


def _union_of(cand, points: np.ndarray) -> bool:
    return len(cand.points) == len(points) and np.allclose(np.sort(cand.points, 0), np.sort(points, 0))


def test_overlapping_candidates_are_examined_first_as_one() -> None:
    from regnf.registration.discovery import Discovery, Tried, examined, overlapping_pairs

    field, cfg, found, whole = _halves()
    cands = found.candidates
    # The halves overlap most; the right half also touches the fourth candidate, but belongs to
    # one pair only. A zero threshold joins nothing.
    assert overlapping_pairs(cands, cfg.join_overlap) == [(0, 1)]
    assert overlapping_pairs(cands, 0.0) == []
    seen: list[int] = []

    def examine(cand):  # the halves' union is the object; the fourth candidate is matched alone
        seen.append(next((k for k, c in enumerate(cands) if c is cand), -1))
        chosen = None
        if _union_of(cand, whole):
            chosen = Tried("obj", 1.0, None)
        elif cand is cands[3]:
            chosen = Tried("other", 0.9, None)
        return Discovery(cand, cand.box, [], chosen)

    out = examined(found, each(examine), lambda d, half: True, field, cfg)
    assert seen == [-1, 2, 3]  # the union first; its halves never on their own
    assert [d.chosen.library_name if d.chosen else None for d in out].count("obj") == 1
    joined = next(d for d in out if d.chosen is not None and d.chosen.library_name == "obj")
    np.testing.assert_allclose(joined.candidate.box.center[:2], [0.5, 0.5], atol=0.03)
    assert len(out) == 3 and any(d.candidate is cands[2] for d in out) and any(d.candidate is cands[3] for d in out)
    volumes = [float(np.prod(d.candidate.box.half_extents)) for d in out]
    assert volumes == sorted(volumes, reverse=True)


def test_a_union_that_does_not_explain_its_halves_yields_to_them() -> None:
    from regnf.registration.discovery import Discovery, Tried, examined

    field, cfg, found, whole = _halves()
    cands = found.candidates

    def examine_with(left_alone: bool):
        def examine(cand):
            chosen = None
            if _union_of(cand, whole):
                chosen = Tried("big", 1.0, None)
            elif cand is cands[0] and left_alone:
                chosen = Tried("small", 0.9, None)
            return Discovery(cand, cand.box, [], chosen)
        return examine

    def left_only(d, half) -> bool:  # the union's object explains the left half alone
        return half is cands[0]

    # One half matched on its own: both halves stay, the union is dropped.
    out = examined(found, each(examine_with(True)), left_only, field, cfg)
    assert sorted(d.chosen.library_name for d in out if d.chosen) == ["small"]
    assert len(out) == 4
    # Neither half matched: the union replaces them, as an unexplained match is still the best.
    out = examined(found, each(examine_with(False)), left_only, field, cfg)
    assert sorted(d.chosen.library_name for d in out if d.chosen) == ["big"]
    assert len(out) == 3
    # A union that matches nothing leaves all four as they were, largest first.
    none = examined(found, each(lambda c: Discovery(c, c.box, [], None)), left_only, field, cfg)
    assert [d.candidate for d in none] == sorted(cands, key=lambda c: -np.prod(c.box.half_extents))
    with pytest.raises(ValueError, match="join_overlap"):
        DiscoveryConfig(join_overlap=2.0)
    with pytest.raises(ValueError, match="half_explained"):
        DiscoveryConfig(half_explained=-0.1)


def test_explained_fraction_measures_metres_to_the_registered_surface() -> None:
    from regnf.fields.analytic import Sphere
    from regnf.registration.discovery import explained_fraction
    from regnf.registration.result import RegistrationResult

    # Scene field frame = metres / 2 (to_world scales by 2); the library sphere, radius 1 in its
    # own units, stands at (1, 0, 0) metres with radius 0.25 m: scene field -> library is x -> 8 (x - (0.5, 0, 0)).
    scene = Box((3.0, 3.0, 0.05), to_world=torch.diag(torch.tensor([2.0, 2.0, 2.0, 1.0])))
    truth = SimilarityTransform.from_matrix(np.asarray(similarity_matrix(np.eye(3), [-4.0, 0.0, 0.0], 8.0)))
    result = RegistrationResult(truth, 0.9, True, "regnf")
    d = np.array([[1.0, 0.0, 1.0]]) / np.sqrt(2.0)
    radii = np.array([0.25, 0.26, 0.27, 0.30, 0.40])[:, None]  # metres from the centre
    points = np.array([1.0, 0.0, 0.0]) + radii * d
    # 0, 1, 2, 5 and 15 cm from the surface: within 3 cm, the first three.
    assert explained_fraction(scene, Sphere(1.0), result, points, 0.03) == pytest.approx(0.6)
    assert explained_fraction(scene, Sphere(1.0), result, points, 0.055) == pytest.approx(0.8)


def test_objects_scoring_near_the_best_are_shortlisted_whatever_the_count() -> None:
    from regnf.fields.oriented_box import OrientedBox
    from regnf.registration.discovery import Ranking
    from regnf.registration.sampling import SurfaceSamples

    empty = SurfaceSamples(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64))
    box = OrientedBox.from_aabb(np.zeros(3), np.ones(3))
    # The low-coverage mix-room's fc box (2026-12-05): three armchairs within 0.012.
    tie = Ranking(box, empty, {"fc-nop": 0.583, "mc": 0.580, "fc": 0.571, "wt": 0.257, "dc": 0.216}, 0.0)
    assert tie.shortlisted(DiscoveryConfig()) == ["fc-nop", "mc", "fc"]
    # (The best, 0.583, is under shortlist_uncertain as well: either rule registers all three.)
    assert tie.shortlisted(DiscoveryConfig(shortlist_margin=0.0)) == ["fc-nop", "mc", "fc"]
    assert tie.shortlisted(DiscoveryConfig(shortlist_margin=0.0, shortlist_uncertain=0.0)) == ["fc-nop", "mc"]
    # A clear best: it alone, the runner-up being further behind than shortlist_gap; with the
    # gap open, the count alone, even when the runner-up and the third are close.
    clear = Ranking(box, empty, {"t": 0.729, "dc": 0.176, "et": 0.166, "c": 0.155}, 0.0)
    assert clear.shortlisted(DiscoveryConfig()) == ["t"]
    assert clear.shortlisted(DiscoveryConfig(shortlist_gap=math.inf)) == ["t", "dc"]
    assert clear.shortlisted(DiscoveryConfig(shortlist=1, shortlist_margin=0.6)) == ["t", "dc", "et", "c"]
    # The demo's room (2026-12-05): a runner-up 0.08 behind is registered, one 0.26 behind is not.
    near = Ranking(box, empty, {"fc": 0.346, "fc-nop": 0.266, "mc": 0.1}, 0.0)
    far = Ranking(box, empty, {"dc": 0.639, "c": 0.377, "mc": 0.004}, 0.0)
    assert near.shortlisted(DiscoveryConfig()) == ["fc", "fc-nop"]
    assert far.shortlisted(DiscoveryConfig()) == ["dc"]
    # No object's pose found (the best scores under 0.6: the demo's fc-nop box, 2026-12-06):
    # everything within the gap, here the right object third; a confident best keeps the count.
    lost = Ranking(box, empty, {"mc": 0.338, "fc": 0.303, "fc-nop": 0.218, "dc": 0.158, "c": 0.110}, 0.0)
    assert lost.shortlisted(DiscoveryConfig()) == ["mc", "fc", "fc-nop"]
    assert lost.shortlisted(DiscoveryConfig(shortlist_uncertain=0.0)) == ["mc", "fc"]
    sure = Ranking(box, empty, {"dc": 0.771, "c": 0.70, "fc": 0.65}, 0.0)
    assert sure.shortlisted(DiscoveryConfig()) == ["dc", "c"]
    for bad in (-0.1, 1.5, math.nan):
        with pytest.raises(ValueError, match="shortlist_uncertain"):
            DiscoveryConfig(shortlist_uncertain=bad)
    with pytest.raises(ValueError, match="shortlist_margin"):
        DiscoveryConfig(shortlist_margin=-0.1)
    with pytest.raises(ValueError, match="shortlist_gap"):
        DiscoveryConfig(shortlist_gap=-0.1)
