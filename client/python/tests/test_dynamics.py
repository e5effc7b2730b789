"""Dynamic-object statistics (issue 16) through the SDK: get_dynamics and Place.dynamics."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone
from typing import Dict

import pytest
from conftest import textured_image

import placedb


#: Monday of last week, 00:00 UTC: timestamps in the past (the server counts those over a day
#: ahead of its clock as "future" and leaves them out of the hour histogram).
_today = datetime.now(timezone.utc).replace(hour=0, minute=0, second=0, microsecond=0)
_MONDAY = _today - timedelta(days=_today.weekday() + 7)


def _utc_ns(weekday: int, hour: int) -> int:
    """Unix nanoseconds of last week's day ``weekday`` (0 = Monday) at ``hour``:30 UTC."""
    moment = _MONDAY + timedelta(days=weekday, hours=hour, minutes=30)
    return int(moment.timestamp()) * 1_000_000_000


@pytest.fixture(scope="module")
def dynamics_map(server) -> Dict[str, int]:
    """Map "dyn": three places with a person over a quarter of the image (Monday 08:30 UTC), a
    car over half of it (Tuesday 18:30) and nothing (Wednesday 12:30); name -> place id."""
    width, height = 320, 240
    frames = {
        "person": placedb.Frame(
            image=textured_image(seed=101),
            boxes=[placedb.Box("person", 0.9, (0, 0, width // 4, height))],
            timestamp_ns=_utc_ns(0, 8),
        ),
        "car": placedb.Frame(
            image=textured_image(seed=102),
            boxes=[placedb.Box("car", 0.9, (0, 0, width // 2, height))],
            timestamp_ns=_utc_ns(1, 18),
        ),
        "empty": placedb.Frame(image=textured_image(seed=103), timestamp_ns=_utc_ns(2, 12)),
    }
    with placedb.Client(server.address) as client:
        # Unrefined boxes: coverage is exactly the boxes' share of the image.
        client.create_map("dyn", placedb.MapSettings(box_refinement="none"))
        results = list(client.ingest("dyn", frames.values(), agent_id="cam"))
    assert all(r.stored for r in results), [r.rejection for r in results]
    return {name: r.place_id for name, r in zip(frames, results)}


def test_places_ranked_by_mean_coverage_and_paged(
    client: placedb.Client, dynamics_map: Dict[str, int]
) -> None:
    answer = client.get_dynamics("dyn")
    assert isinstance(answer, placedb.Dynamics)
    assert [p.place_id for p in answer.places] == [
        dynamics_map["car"],
        dynamics_map["person"],
        dynamics_map["empty"],
    ]
    car, person, empty = answer.places
    assert car.score == pytest.approx(0.5, abs=0.01)
    assert person.score == pytest.approx(0.25, abs=0.01)
    assert empty.score == 0.0
    assert all(p.support == 1 and p.statistics is None for p in answer.places)
    assert (answer.ranked, answer.next_offset) == (3, 0)

    whole = answer.map
    assert whole.observations == 3
    assert whole.mean_coverage == pytest.approx(0.25, abs=0.01)
    assert whole.max_coverage == pytest.approx(0.5, abs=0.01)
    assert whole.last_timestamp_ns == _utc_ns(2, 12)
    assert whole.last_coverage == 0.0
    assert (whole.untimed, whole.future) == (0, 0)
    assert [(c.class_id, c.frames, c.boxes) for c in whole.classes] == [(0, 1, 1), (2, 1, 1)]
    assert [(h.weekday, h.hour, h.observations) for h in whole.hours] == [
        (0, 8, 1),
        (1, 18, 1),
        (2, 12, 1),
    ]
    assert answer.invalid.observations == 0

    # Pages of one walk every place once, in the same order; past the end is empty.
    seen, offset = [], 0
    while True:
        page = client.get_dynamics("dyn", limit=1, offset=offset)
        seen += [p.place_id for p in page.places]
        if page.next_offset == 0:
            break
        offset = page.next_offset
    assert seen == [p.place_id for p in answer.places]
    assert client.get_dynamics("dyn", offset=10).places == []

    detailed = client.get_dynamics("dyn", include_statistics=True).places[0]
    assert detailed.statistics is not None
    assert [c.class_id for c in detailed.statistics.classes] == [2]


def test_class_share_and_hour_window(
    client: placedb.Client, dynamics_map: Dict[str, int]
) -> None:
    by_name = client.get_dynamics("dyn", class_name="person")
    assert by_name.places[0].place_id == dynamics_map["person"]
    assert by_name.places[0].score == 1.0
    assert [p.score for p in by_name.places[1:]] == [0.0, 0.0]
    by_id = client.get_dynamics("dyn", measure="class_share", class_id=2)
    assert by_id.places[0].place_id == dynamics_map["car"]

    evening = client.get_dynamics("dyn", hours=(17, 19))
    assert [p.place_id for p in evening.places] == [dynamics_map["car"]]
    assert evening.places[0].score == pytest.approx(0.5, abs=0.01)
    assert client.get_dynamics("dyn", hours=(17, 19), weekdays=["tue"]).places
    assert client.get_dynamics("dyn", hours=(17, 19), weekdays=["mon", 2]).places == []
    overnight = client.get_dynamics("dyn", hours=(20, 9), weekdays=["Monday"])
    assert [p.place_id for p in overnight.places] == [dynamics_map["person"]]


def test_place_carries_its_dynamics(client: placedb.Client, dynamics_map: Dict[str, int]) -> None:
    person = client.get_place("dyn", dynamics_map["person"])
    assert person.dynamics is not None
    assert person.dynamics.observations == 1
    assert person.dynamics.mean_coverage == pytest.approx(0.25, abs=0.01)
    assert [(c.class_id, c.frames) for c in person.dynamics.classes] == [(0, 1)]
    assert [(h.weekday, h.hour) for h in person.dynamics.hours] == [(0, 8)]
    empty = client.get_place("dyn", dynamics_map["empty"])
    assert empty.dynamics is not None and empty.dynamics.classes == []


def test_bad_dynamics_requests_name_their_field(
    client: placedb.Client, dynamics_map: Dict[str, int]
) -> None:
    with pytest.raises(placedb.NotFound, match="absent"):
        client.get_dynamics("absent")
    server_side = [
        (dict(limit=5000), "limit"),
        (dict(class_name="unicorn"), "class_name"),
        (dict(class_name="person", class_id=2), "class"),
        (dict(hours=(25, 3)), "hour"),
    ]
    for arguments, field in server_side:
        with pytest.raises(placedb.InvalidArgument, match=field):
            client.get_dynamics("dyn", **arguments)
    client_side = [
        (dict(limit=-1), "limit"),
        (dict(measure="loudness"), "measure"),
        (dict(hours=(1,)), "hours"),
        (dict(hours=(1, 2), weekdays=["funday"]), "weekdays"),
        (dict(hours=(1, 2), weekdays=[7]), "weekdays"),
        (dict(hours=(1, 2), weekdays=[]), "weekdays"),
    ]
    for arguments, field in client_side:
        with pytest.raises(placedb.InvalidArgument, match=field):
            client.get_dynamics("absent", **arguments)  # refused before it is sent
