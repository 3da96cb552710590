import itertools
import json
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sonarloc.io.logfile import SensorMount
from sonarloc.world.rig import (
    PanRig,
    RingRig,
    load_rig,
    pan_angles_deg,
    parse_pan_schedule,
    rig_by_name,
    rig_from_json,
    rig_to_json,
    ring16,
    save_rig,
)


def test_ring16_layout_and_groups():
    rig = ring16()
    assert len(rig.sensors) == 16
    for i, m in enumerate(rig.sensors):
        assert m.id == i and m.yaw_deg == pytest.approx(22.5 * i)
        assert math.hypot(m.x_m, m.y_m) == pytest.approx(0.2)
        assert math.degrees(math.atan2(m.y_m, m.x_m)) % 360 == pytest.approx(22.5 * i, abs=1e-6)
    assert sorted(itertools.chain.from_iterable(rig.groups)) == list(range(16))
    for g in rig.groups:  # no two neighbours fire together
        for a, b in itertools.combinations(g, 2):
            assert min((a - b) % 16, (b - a) % 16) > 1
    fire = list(itertools.islice(rig.firings(), 5))
    assert [f[0] for f in fire] == pytest.approx([0.0, 0.03, 0.06, 0.09, 0.12])
    assert fire[4][1] == fire[0][1] and all(p is None for _, p in fire[0][1])


def test_pan_schedule():
    assert len(pan_angles_deg(-40, 40, 0.3)) == 267
    assert pan_angles_deg(10, -10, -5).tolist() == [10, 5, 0, -5, -10]
    rig = PanRig(pan_deg=(-1.0, 1.0, 1.0), repeat=2, ping_period_s=0.05)
    fire = list(itertools.islice(rig.firings(), 8))
    assert [f[1][0][1] for f in fire] == [-1, -1, 0, 0, 1, 1, -1, -1]
    assert fire[7][0] == pytest.approx(0.35)
    assert rig.sweep_s == pytest.approx(0.3)
    assert parse_pan_schedule("-40:40:0.3") == (-40.0, 40.0, 0.3)


@pytest.mark.parametrize("text", ["-40:40", "a:b:c", "-40:40:0", "40:-40:1", "0:1:nan", ""])
def test_bad_pan_schedule_names_the_value(text):
    with pytest.raises(ValueError, match="pan schedule"):
        parse_pan_schedule(text)


mount = st.builds(SensorMount, st.integers(0, 99), st.floats(-1, 1), st.floats(-1, 1),
                  st.floats(-180, 180))


@st.composite
def rigs(draw):
    if draw(st.booleans()):
        start = draw(st.floats(-90, 0))
        return PanRig(draw(mount), (start, start + draw(st.floats(0, 90)),
                                    draw(st.floats(0.1, 5))),
                      draw(st.integers(1, 100)), draw(st.floats(0.01, 1)),
                      draw(st.one_of(st.none(), st.floats(0.2, 10))))
    mounts = draw(st.lists(mount, min_size=1, max_size=8, unique_by=lambda m: m.id))
    ids = [m.id for m in mounts]
    groups = draw(st.lists(st.lists(st.sampled_from(ids), min_size=1, max_size=3),
                           min_size=1, max_size=4))
    return RingRig(tuple(mounts), tuple(tuple(g) for g in groups), draw(st.floats(0.005, 0.2)),
                   draw(st.one_of(st.none(), st.floats(0.2, 10))))


@settings(max_examples=60, deadline=None)
@given(rigs())
def test_rig_json_round_trip(tmp_path_factory, rig):
    assert rig_from_json(json.loads(json.dumps(rig_to_json(rig)))) == rig
    path = tmp_path_factory.mktemp("rig") / "rig.json"
    save_rig(rig, path)
    assert load_rig(path) == rig


@pytest.mark.parametrize(
    ("obj", "match"),
    [
        ([], "JSON object"),
        ({}, "field `kind` is missing"),
        ({"kind": "star"}, "field `kind` must be 'pan' or 'ring'"),
        ({"kind": "ring"}, "field `sensors` is missing"),
        ({"kind": "ring", "sensors": []}, "field `sensors` must be a non-empty list"),
        ({"kind": "ring", "sensors": [{"id": "a"}]}, r"field `sensors\[0\].id`"),
        ({"kind": "ring", "sensors": [{"id": 0, "x_m": "1"}]}, r"field `sensors\[0\].x_m`"),
        ({"kind": "ring", "sensors": [{"id": 0}], "slot_s": -1}, "field `slot_s`.*-1"),
        ({"kind": "ring", "sensors": [{"id": 0}], "groups": [[1]]}, r"`groups\[0\]`.*id 1"),
        ({"kind": "ring", "sensors": [{"id": 0}], "groups": "0"}, "field `groups`"),
        ({"kind": "ring", "sensors": [{"id": 0}, {"id": 0}]}, "`sensors` ids must be unique"),
        ({"kind": "pan", "sensors": [{"id": 0}, {"id": 1}]}, "exactly one"),
        ({"kind": "pan", "sensors": [{"id": 0}], "pan": {"start_deg": 0, "stop_deg": 1}},
         "field `pan.step_deg`"),
        ({"kind": "pan", "sensors": [{"id": 0}], "repeat": 0}, "field `repeat`.*0"),
        ({"kind": "pan", "sensors": [{"id": 0}], "range_gate_m": -2}, "field `range_gate_m`"),
    ],
)
def test_bad_rig_names_the_field(obj, match):
    with pytest.raises(ValueError, match=match):
        rig_from_json(obj)


def test_rig_files_and_names(tmp_path):
    path = tmp_path / "r.json"
    path.write_text('{"kind": "pan", "sensors": [{"id": 3, "x_m": 0.1, "y_m": 0, "yaw_deg": 0}],'
                    ' "pan": "-10:10:2", "repeat": 3}')
    rig = rig_by_name(str(path))
    assert isinstance(rig, PanRig) and rig.sensor.id == 3 and rig.repeat == 3
    assert len(rig.angles_deg) == 11
    assert rig_by_name(str(path), pan=(0, 4, 2), repeat=1).angles_deg.tolist() == [0, 2, 4]
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(ValueError, match="bad.json: not JSON"):
        load_rig(tmp_path / "bad.json")
    with pytest.raises(ValueError, match="got 'ring17'"):
        rig_by_name("ring17")
    with pytest.raises(ValueError, match="need a pan rig"):
        rig_by_name("ring16", repeat=2)


json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-3, 20) | st.floats(allow_nan=True)
    | st.sampled_from(["pan", "ring", "-40:40:0.3", "x"]),
    lambda children: st.lists(children, max_size=4)
    | st.dictionaries(st.sampled_from(["kind", "sensors", "groups", "slot_s", "pan", "repeat",
                                       "ping_period_s", "range_gate_m", "id", "x_m", "yaw_deg",
                                       "start_deg", "stop_deg", "step_deg"]),
                      children, max_size=6),
    max_leaves=20)


@settings(max_examples=300, deadline=None)
@given(json_values)
def test_garbage_rigs_give_rig_or_valueerror(obj):
    try:
        rig = rig_from_json(obj)
    except ValueError as err:
        assert str(err)
        return
    assert rig_from_json(rig_to_json(rig)) == rig
