"""The `actor` dim: people, riders and large vehicles as the object under test, on our streets
and in real scans, with SemanticKITTI's classes, where they may stand, and the objective that
follows from them."""

from __future__ import annotations

import copy
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from falsify.classes import CAR, CYCLIST, PEDESTRIAN, UNKNOWN
from falsify.data.real_backgrounds import INSERTED_INSTANCE, RealScanner, scanner_for
from falsify.errors import ConfigError
from falsify.results.metrics import Scoring
from falsify.semantic import RAW_ID, TRAIN_CLASSES
from falsify.sensor.lidar import load_sensor
from falsify.sensor.scanner import FIRST_CAR_INSTANCE, InvalidSample
from falsify.sensor.simulator import Simulator
from falsify.world.actors import ACTOR_NAMES, BUILTIN_ACTORS, actor_model, model_semantic
from falsify.world.cars import BUILTIN_MODELS
from falsify.world.space import parse_space
from tests.data.test_real_backgrounds import WALL_X, street_cloud, write_scan

# The class each built-in actor's points carry, in the four-class view and as raw ids.
EXPECTED = {
    "pedestrian": (PEDESTRIAN, "person"), "pedestrian-walking": (PEDESTRIAN, "person"),
    "pedestrian-running": (PEDESTRIAN, "person"), "child": (PEDESTRIAN, "person"),
    "cyclist": (CYCLIST, "bicyclist"), "motorcyclist": (CYCLIST, "motorcyclist"),
    "bicycle": (UNKNOWN, "bicycle"), "truck": (UNKNOWN, "truck"), "bus": (UNKNOWN, "bus"),
    "other-vehicle": (UNKNOWN, "other-vehicle"),
}
BASE = {"dims": {"actor": {"values": ["pedestrian"]}, "x": {"values": [0.0]},
                 "y": {"values": [10.0]}, "background": {"values": [0]}}}


def space(actor: str | list[str] = "pedestrian", x: float = 0.0, y: float = 10.0,
          extra: dict | None = None, **table):
    raw = copy.deepcopy(BASE)
    raw["dims"]["actor"] = {"values": [actor] if isinstance(actor, str) else actor, **table}
    raw["dims"]["x"] = {"values": [x]}
    raw["dims"]["y"] = {"values": [y]}
    raw.update(extra or {})
    return parse_space(raw)


def test_every_built_in_actor_is_listed_with_a_class():
    assert set(ACTOR_NAMES) == set(EXPECTED)
    assert not set(ACTOR_NAMES) & set(BUILTIN_MODELS)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_each_actor_is_cast_on_our_streets_with_its_class(name):
    cls, raw = EXPECTED[name]
    sp = space(name)
    scan = scanner_for(sp).scan(sp.grid()[0])
    mine = scan.instance == FIRST_CAR_INSTANCE
    assert mine.sum() > 30, f"{name} barely seen: {mine.sum()} points"
    assert set(np.unique(scan.image[..., 5][mine])) == {cls}
    assert set(np.unique(scan.semantic[mine])) == {RAW_ID[raw]}


def test_actor_meshes_are_closed_to_writes_and_have_the_size_of_their_kind():
    sizes = {}
    for name in ACTOR_NAMES:
        v, f, mat = actor_model(name)
        assert not v.flags.writeable and len(f) == len(mat)
        assert v[:, 2].min() == pytest.approx(0.0, abs=1e-6)   # stands on the ground
        sizes[name] = v.max(axis=0) - v.min(axis=0)
    assert sizes["child"][2] < 1.3 < sizes["pedestrian"][2] < 2.0
    assert sizes["pedestrian-running"][0] > sizes["pedestrian"][0]   # a longer stride
    assert 1.5 < sizes["motorcyclist"][0] < 2.5 and sizes["bus"][0] > 9.0


def test_actor_and_car_model_name_the_same_dim_and_cast_the_same_scan():
    alias = copy.deepcopy(BASE)
    alias["dims"]["car_model"] = alias["dims"].pop("actor")
    old = parse_space(copy.deepcopy(alias) | {"dims": {**alias["dims"],
                                                       "car_model": {"values": ["sedan"]}}})
    new = space("sedan")
    assert old.model_dim == "car_model" and new.model_dim == "actor"
    a, b = (scanner_for(s).scan(s.grid()[0]) for s in (old, new))
    assert a.image.tobytes() == b.image.tobytes()
    assert a.semantic.tobytes() == b.semantic.tobytes()
    assert old.grid()[0].values[0] == ("car_model", "sedan")   # old configs keep their rows


def test_a_second_actor_has_its_own_dims_and_occludes_the_first():
    raw = copy.deepcopy(BASE)
    raw["dims"].update({"actor_2": {"values": ["truck"]}, "y": {"values": [14.0]},
                        "y_2": {"values": [7.5]}, "count": {"values": [1, 2]}})
    sp = parse_space(raw)
    assert set(sp.dims) >= {"actor_2", "x_2", "y_2", "yaw_2"}
    s = sp.make({"count": 2})
    assert [c.model for c in s.cars] == ["pedestrian", "truck"]
    scan = scanner_for(sp).scan(s)
    assert (scan.instance == FIRST_CAR_INSTANCE).sum() == 0   # the truck hides the person
    alone = scanner_for(sp).scan(sp.make({"count": 1}))
    assert (alone.instance == FIRST_CAR_INSTANCE).sum() > 30


def _street_positions(sim: Simulator) -> tuple[float, float, float]:
    """A road, a sidewalk and a terrain position (space x) at y = 10 m on street 0."""
    sim.background(0)
    t = sim._terrain[0]
    kerb = float(t.kerb(10.0))
    return 0.0, -(kerb + t.sidewalk[0] / 2), -(kerb + t.sidewalk[0] + 3.0)


def test_on_keeps_actors_on_their_surface_of_our_streets():
    sim = scanner_for(space())
    road, sidewalk, terrain = _street_positions(sim)
    for on, ok, bad in (("sidewalk", sidewalk, road), ("road", road, sidewalk)):
        sp = space(x=ok, on=on)
        scanner = scanner_for(sp)
        scanner.scan(sp.grid()[0])
        with pytest.raises(InvalidSample, match=rf"actor 1 \(pedestrian\) stands on \w+, not on "
                                                rf"the {on}"):
            scanner.scan(space(x=bad, on=on).grid()[0])
    sp = space(x=terrain, on="sidewalk")
    with pytest.raises(InvalidSample, match="stands on terrain"):
        scanner_for(sp).scan(sp.grid()[0])


def test_a_person_crosses_the_kerb_where_a_truck_cannot():
    sim = scanner_for(space())
    _, sidewalk, _ = _street_positions(sim)
    person = space(x=sidewalk)
    scanner_for(person).scan(person.grid()[0])
    truck = space("truck", x=sidewalk)
    with pytest.raises(InvalidSample, match="curb"):
        scanner_for(truck).scan(truck.grid()[0])


def test_invalid_reasons_name_an_actor_as_the_report_does():
    """An actor is "actor N" in the reasons of invalid samples, as in the report; a car stays
    "car N"."""
    at_ego = space(x=0.0, y=0.0)
    with pytest.raises(InvalidSample, match=r"^actor 1 \(pedestrian\) intersects the ego "):
        scanner_for(at_ego).scan(at_ego.grid()[0])
    raw = copy.deepcopy(BASE)
    raw["dims"].update({"actor_2": {"values": ["truck"]}, "x_2": {"values": [0.3]},
                        "y_2": {"values": [10.0]}, "count": {"values": [2]}})
    both = parse_space(raw)
    with pytest.raises(InvalidSample, match=r"^actor 2 \(truck\) intersects actor 1 "
                                            r"\(pedestrian\)$"):
        scanner_for(both).scan(both.grid()[0])
    cars = parse_space({"dims": {"car_model": {"values": ["sedan"]}, "x": {"values": [0.0]},
                                 "y": {"values": [0.0]}, "background": {"values": [0]}}})
    with pytest.raises(InvalidSample, match=r"^car 1 \(sedan\) intersects the ego vehicle$"):
        scanner_for(cars).scan(cars.grid()[0])


@pytest.fixture(scope="module")
def kerbside(tmp_path_factory):
    """The constructed real street, its ground right of y = -3 m labelled sidewalk."""
    pts, sem = street_cloud()
    sem = np.where((pts[:, 1] < -3.0) & (sem == RAW_ID["road"]), RAW_ID["sidewalk"], sem)
    return write_scan(tmp_path_factory.mktemp("kerbside"), pts, sem.astype(np.uint32))


def real_space(real, actor="pedestrian", x=0.0, **table):
    raw = copy.deepcopy(BASE)
    raw["dims"]["actor"] = {"values": [actor], **table}
    raw["dims"]["x"] = {"values": [x]}
    raw["dims"]["background"] = {"real": [str(real.bin)]}
    return parse_space(raw)


@pytest.mark.parametrize("name", ["pedestrian", "cyclist", "motorcyclist", "bus"])
def test_actors_are_inserted_into_a_real_scan_with_their_class(kerbside, name):
    sp = real_space(kerbside, name)
    scan = scanner_for(sp).scan(sp.grid()[0])
    mine = scan.instance == INSERTED_INSTANCE
    cls, raw = EXPECTED[name]
    assert mine.sum() > 30
    assert set(np.unique(scan.semantic[mine])) == {RAW_ID[raw]}
    assert set(np.unique(scan.image[..., 5][mine])) == {cls}


def test_an_actor_in_a_real_scans_wall_is_named_as_an_actor(kerbside):
    raw = copy.deepcopy(BASE)
    raw["dims"].update({"actor": {"values": ["truck"]}, "y": {"values": [WALL_X]},
                        "background": {"real": [str(kerbside.bin)]}})
    sp = parse_space(raw)
    with pytest.raises(InvalidSample, match=r"^actor 1 \(truck\) intersects the real scan's "
                                            r"building"):
        scanner_for(sp).scan(sp.grid()[0])


def test_on_reads_the_surface_from_a_real_scans_labels(kerbside):
    scanner = RealScanner(load_sensor("kitti-hdl64e-front"), (kerbside,))
    bg = scanner.background(0)
    assert scanner.surface(bg, 10.0, 0.0) == "road"
    assert scanner.surface(bg, 10.0, -6.0) == "sidewalk"
    assert scanner.surface(bg, 300.0, 0.0) == "unlabelled ground"
    ok = real_space(kerbside, x=6.0, on="sidewalk")   # space x = 6 m right: world y = -6
    scanner_for(ok).scan(ok.grid()[0])
    bad = real_space(kerbside, x=0.0, on="sidewalk")
    with pytest.raises(InvalidSample, match="stands on road, not on the sidewalk"):
        scanner_for(bad).scan(bad.grid()[0])


@pytest.mark.parametrize("mutate, message", [
    (lambda r: r["dims"]["actor"].update(values=["tank"]), "dims.actor: unknown actor 'tank'"),
    (lambda r: r["dims"]["actor"].update(on="verge"), "dims.actor.on: 'verge'; allowed: any, "
                                                      "road, sidewalk"),
    (lambda r: r["dims"].update(car_model={"values": ["sedan"]}), "give one of them"),
    (lambda r: r.update(actors={"dog": {"file": "dog.obj"}}), "actors.dog.class: missing"),
    (lambda r: r.update(actors={"dog": {"file": "dog.obj", "class": "animal"}}),
     "actors.dog.class: 'animal'; a user's actor declares its SemanticKITTI class, one of: car"),
    (lambda r: r.update(actors={"child": {"file": "c.obj", "class": "person"}}),
     "actors.child: 'child' is a built-in or declared model"),
    (lambda r: r.update(actors={"dog": {"file": "d.obj", "class": "person", "legs": 4}}),
     "actors.dog: unknown key 'legs'"),
])
def test_bad_actor_configs_name_the_key(mutate, message):
    raw = copy.deepcopy(BASE)
    mutate(raw)
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(".", r"\.")):
        parse_space(raw)


def test_on_needs_labels_on_real_backgrounds(tmp_path):
    pts, _ = street_cloud()
    bare = write_scan(tmp_path, pts, None)
    with pytest.raises(ConfigError, match=r"dims\.actor\.on: 'road' reads where the road"):
        real_space(bare, on="road")
    real_space(bare, on="any")


def test_a_user_actor_carries_its_declared_class(tmp_path):
    import trimesh
    trimesh.creation.box(extents=(0.6, 0.5, 1.7)).export(tmp_path / "post.obj")
    sp = space("mine", extra={"actors": {"mine": {"file": str(tmp_path / "post.obj"),
                                                  "class": "person"}}})
    assert sp.user_cars["mine"].semantic == RAW_ID["person"]
    assert model_semantic("mine", sp.user_cars) == RAW_ID["person"]
    scan = scanner_for(sp).scan(sp.grid()[0])
    mine = scan.instance == FIRST_CAR_INSTANCE
    assert mine.sum() > 30 and set(np.unique(scan.image[..., 5][mine])) == {PEDESTRIAN}


def test_the_default_objective_is_the_placed_actors_class():
    four = ["unknown", "car", "pedestrian", "cyclist"]
    sem = list(TRAIN_CLASSES)
    person, rider, car = RAW_ID["person"], RAW_ID["bicyclist"], RAW_ID["car"]
    assert Scoring.placed_class(four, [car]) == "car"
    assert Scoring.placed_class(four, [person]) == "pedestrian"
    assert Scoring.placed_class(four, [rider, RAW_ID["motorcyclist"]]) == "cyclist"
    assert Scoring.placed_class(sem, [person]) == "person"
    assert Scoring.placed_class(sem, [RAW_ID["bus"]]) == "other-vehicle"
    with pytest.raises(ConfigError, match="the placed actors are car, pedestrian"):
        Scoring.placed_class(four, [car, person])
    with pytest.raises(ConfigError, match="the placed actors are unknown"):
        Scoring.placed_class(four, [RAW_ID["truck"]])
    assert {BUILTIN_ACTORS[n].semantic for n in ("pedestrian", "child")} == {person}
    assert CAR == 1


def run(cfg: Path, out: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "falsify", "grid", str(cfg), "--out", str(out),
                           "--json", *args], capture_output=True, text=True)


def test_a_pedestrian_grid_on_a_real_background_scores_the_person(tmp_path, kerbside):
    cfg = tmp_path / "ped.toml"
    cfg.write_text(f"""name = "ped"
[dims.actor]
values = ["pedestrian", "child"]
on = "any"
[dims.x]
values = [-1.0, 2.0]
[dims.y]
values = [8.0, 12.0]
[dims.background]
real = ['{kerbside.bin}']
""")
    out = tmp_path / "run"
    proc = run(cfg, out)
    assert proc.returncode == 0, proc.stderr
    with sqlite3.connect(out / "results.sqlite") as con:
        rows = con.execute("SELECT actor, status, pedestrian_iou, inserted_iou FROM samples"
                           ).fetchall()
    assert len(rows) == 8 and all(r[1] == "ok" and r[3] is not None for r in rows)
    assert {r[0] for r in rows} == {"pedestrian", "child"}
    html = (out / "report.html").read_text()
    assert "<th>actor</th>" in html and "pedestrian IoU" in html
    mixed = tmp_path / "mixed.toml"
    mixed.write_text(cfg.read_text().replace('"child"', '"sedan"'))
    proc = run(mixed, tmp_path / "mixed")
    assert proc.returncode == 2 and "--objective" in proc.stderr
    assert "car, pedestrian" in proc.stderr and not (tmp_path / "mixed").exists()
    proc = run(mixed, tmp_path / "mixed", "--objective", "pedestrian", "--no-report")
    assert proc.returncode == 0, proc.stderr
    with sqlite3.connect(tmp_path / "mixed" / "results.sqlite") as con:
        rows = con.execute("SELECT actor, inserted_car_iou, inserted_car_recall, "
                           "inserted_pedestrian_iou, inserted_pedestrian_recall, inserted_iou "
                           "FROM samples WHERE status = 'ok'").fetchall()
    # Each placed class scored apart: a sample's own class has a recall, the other none.
    for actor, car_iou, car_rec, ped_iou, ped_rec, objective in rows:
        assert (car_rec is None) == (actor != "sedan") and (ped_rec is None) == (actor == "sedan")
        assert ped_iou == objective
        assert actor != "sedan" or car_iou is not None
    assert {r[0] for r in rows} == {"sedan", "pedestrian"}
    with sqlite3.connect(out / "results.sqlite") as con:   # one class placed: no extra columns
        names = [r[1] for r in con.execute("PRAGMA table_info(samples)")]
    assert "inserted_iou" in names and not any(n.startswith("inserted_pedestrian") for n in names)


def test_the_report_of_a_person_run_names_the_class_and_escapes_the_actor(tmp_path, kerbside,
                                                                           browser):
    """A user's actor named like markup, class person, in a real scan: the report's sections
    name pedestrians, its tables show the name as text, and the page fetches nothing."""
    import trimesh
    from selenium.webdriver.common.by import By

    from tests.conftest import assert_offline

    odd = 'kid<b>&"x'
    trimesh.creation.box(extents=(0.5, 0.4, 1.2)).export(tmp_path / "kid.obj")
    cfg = tmp_path / "odd.toml"
    cfg.write_text(f"""name = "odd"
[actors.'{odd}']
file = "kid.obj"
class = "person"
[dims.actor]
values = ['{odd}']
[dims.x]
values = [-1.0, 2.0]
[dims.y]
values = [8.0]
[dims.background]
real = ['{kerbside.bin}']
""")
    out = tmp_path / "run"
    assert run(cfg, out).returncode == 0
    html = (out / "report.html").read_text()
    assert odd not in html and "kid&lt;b&gt;&amp;&quot;x" in html
    browser.get((out / "report.html").as_uri())
    heading = browser.find_element(By.CSS_SELECTOR, "#inserted h2")
    assert heading.text == "Inserted and real pedestrians"
    cells = [td.text for td in browser.find_elements(By.CSS_SELECTOR, "td")]
    assert odd in cells
    assert not browser.find_elements(By.CSS_SELECTOR, "td b")
    # The worst table counts the pedestrians' points (label / predicted), not the cars'.
    heads = [th.text for th in browser.find_elements(By.CSS_SELECTOR, "#worst-section th")]
    assert "pedestrian points\nlabel / pred." in heads, heads
    rows = pd.read_csv(out / "results.csv")
    want = {f"{int(r.pedestrian_tp + r.pedestrian_fn)} / {int(r.pedestrian_tp + r.pedestrian_fp)}"
            for r in rows.itertuples()}
    assert want <= set(cells), (want, cells)
    assert_offline(browser)


@pytest.mark.parametrize("table, named", [
    ('values = ["tank"]', "dims.actor: unknown actor 'tank'"),
    ('values = ["pedestrian"]\non = "verge"', "dims.actor.on: 'verge'"),
])
def test_bad_actor_keys_exit_2_from_the_cli_and_write_nothing(tmp_path, table, named):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(f"[dims.actor]\n{table}\n[dims.x]\nvalues = [0.0]\n[dims.y]\n"
                   "values = [10.0]\n[dims.background]\nvalues = [0]\n")
    proc = run(cfg, tmp_path / "run")
    assert proc.returncode == 2 and named in proc.stderr
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("table, body", [("actors", 'class = "person"\n'), ("car_models", "")])
@pytest.mark.parametrize("content", [None, "not a mesh\n"])
def test_a_users_broken_mesh_is_named_by_its_key(tmp_path, table, body, content):
    """A missing or unreadable mesh names the config and its table ("bad.toml: actors.kid.file"),
    exit 2, no run folder."""
    if content is not None:
        (tmp_path / "kid.obj").write_text(content)
    dim = "actor" if table == "actors" else "car_model"
    cfg = tmp_path / "bad.toml"
    cfg.write_text(f'[{table}.kid]\nfile = "kid.obj"\n{body}[dims.{dim}]\nvalues = ["kid"]\n'
                   "[dims.x]\nvalues = [0.0]\n[dims.y]\nvalues = [10.0]\n[dims.background]\n"
                   "values = [0]\n")
    proc = run(cfg, tmp_path / "run")
    assert proc.returncode == 2, proc.stderr
    assert f"bad.toml: {table}.kid.file {tmp_path / 'kid.obj'}: " in proc.stderr, proc.stderr
    assert not (tmp_path / "run").exists()
