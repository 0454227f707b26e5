"""The object catalog: counts, flags, validation, priors and that every recipe builds."""

from __future__ import annotations

import dataclasses
import math
import random

import pybullet as p
import pytest

import tidee.server.catalog as catalog
from tidee.server.catalog import (
    CATEGORIES,
    PRIORS,
    ROOM_TEMPLATES,
    ROOM_TYPES,
    is_plausible,
    look,
    receptacle_types,
    receptacle_weights,
    sample_size,
    validate_catalog,
    variant_weights,
)
from tidee.server.catalog.schema import Part

AI2THOR_PICKUPABLE = (
    "AlarmClock Apple Book Bowl Bread ButterKnife Candle CellPhone Cloth CreditCard Cup DishSponge Egg "
    "Fork Kettle KeyChain Knife Ladle Laptop Lettuce Mug Newspaper Pan Pen Pencil PepperShaker Pillow "
    "Plate Pot Potato RemoteControl SaltShaker SoapBar SoapBottle Spatula Spoon SprayBottle Statue "
    "TeddyBear TissueBox ToiletPaper Tomato Towel Vase Watch WineBottle"
).split()
RECEPTACLES = (
    "ArmChair Bathtub Bed Cabinet CoffeeTable CounterTop Desk DiningTable Drawer Dresser Fridge GarbageCan "
    "Microwave Ottoman Shelf SideTable Sink Sofa Stool Toilet TowelHolder TVStand Floor Chair "
    "ToiletPaperHanger"
).split()


# ------------------------------------------------------------------ counts & flags


def test_counts() -> None:
    cats = CATEGORIES.values()
    assert len(CATEGORIES) >= 60
    assert sum(c.pickupable for c in cats) >= 35
    assert sum(c.receptacle for c in cats) >= 20
    assert sum(c.openable for c in cats) >= 5
    assert sum(len(c.variants) > 0 for c in cats) >= 8


def test_required_categories_and_flags() -> None:
    for name in AI2THOR_PICKUPABLE:
        assert CATEGORIES[name].pickupable, name
    for name in RECEPTACLES:
        assert CATEGORIES[name].receptacle, name
    for name in ("Fridge", "Cabinet", "Drawer", "Microwave", "Box"):
        assert CATEGORIES[name].openable, name
    for name in (
        "Television",
        "FloorLamp",
        "DeskLamp",
        "Painting",
        "Window",
        "HousePlant",
        "Mirror",
        "LightSwitch",
        "Wall",
        "CoffeeMachine",
        "Toaster",
        "StoveBurner",
        "Faucet",
        "ShowerHead",
    ):
        assert name in CATEGORIES and not CATEGORIES[name].pickupable, name
    assert CATEGORIES["Box"].pickupable and CATEGORIES["Box"].receptacle
    for name, c in CATEGORIES.items():
        assert c.name == name
        if c.placement == "wall_mounted":
            assert c.mount_height > 0


def test_openables_have_doors_and_inside_surfaces() -> None:
    for c in CATEGORIES.values():
        if c.openable:
            assert any(part.door for part in c.parts), c.name
            assert any(s.inside for s in c.surfaces), c.name


def test_sizes_are_realistic() -> None:
    def mid(name: str) -> tuple[float, ...]:
        c = CATEGORIES[name]
        return tuple((a + b) / 2 for a, b in zip(c.size_min, c.size_max))

    assert 0.08 <= mid("Mug")[2] <= 0.12
    assert 1.6 <= mid("Fridge")[2] <= 2.0
    assert 0.72 <= mid("DiningTable")[2] <= 0.78
    assert 0.85 <= mid("CounterTop")[2] <= 0.95 and 0.55 <= mid("CounterTop")[1] <= 0.7
    assert 1.4 <= CATEGORIES["Bed"].size_min[0] and CATEGORIES["Bed"].size_max[0] <= 2.0
    for c in CATEGORIES.values():
        if c.pickupable:
            assert 0 < c.mass < 20, c.name


def test_sample_size_within_range() -> None:
    rng = random.Random(0)
    for name, c in CATEGORIES.items():
        for var in (None, *[v.name for v in c.variants]):
            lk = look(name, var)
            s = sample_size(name, var, rng)
            assert all(a - 1e-9 <= x <= b + 1e-9 for a, x, b in zip(lk.size_min, s, lk.size_max))


def test_variants_differ_in_look() -> None:
    for c in CATEGORIES.values():
        looks = [look(c.name, v.name) for v in c.variants]
        for i, a in enumerate(looks):
            for b in looks[i + 1 :]:
                assert (a.size_min, a.parts, a.palettes) != (b.size_min, b.parts, b.palettes), c.name


# ---------------------------------------------------------------------- validation


def test_catalog_validates() -> None:
    validate_catalog()


def test_broken_prior_receptacle_raises() -> None:
    priors = catalog.load_priors()
    priors["Mug"]["*"]["Kitchen"]["Bed"] = 0.5
    with pytest.raises(ValueError, match=r"Mug.*Kitchen.*'Bed' never appears in a Kitchen"):
        validate_catalog(priors=priors)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda pr: pr["Mug"]["*"]["Kitchen"].update({"Spaceship": 1.0}), "unknown receptacle 'Spaceship'"),
        (lambda pr: pr["Mug"]["*"]["Kitchen"].update({"Apple": 1.0}), "'Apple' is not a receptacle"),
        (lambda pr: pr.update({"Fridge": {"*": {"Kitchen": {"Floor": 1.0}}}}), "Fridge is not pickupable"),
        (
            lambda pr: pr["Vase"].update({"enormous": {"Kitchen": {"Floor": 1.0}}}),
            "unknown variant 'enormous'",
        ),
        (lambda pr: pr["Mug"]["*"]["Kitchen"].update({"Shelf": -1}), "must be a positive number"),
        (lambda pr: pr.pop("Mug"), "Mug: pickupable but has no placement prior"),
    ],
)
def test_broken_priors_raise(mutate, message: str) -> None:  # type: ignore[no-untyped-def]
    priors = catalog.load_priors()
    mutate(priors)
    with pytest.raises(ValueError, match=message):
        validate_catalog(priors=priors)


def test_broken_rooms_raise() -> None:
    rooms = catalog.load_room_templates()
    tv = {"type": "Television", "count": [1, 1], "required": True, "on": "TVStand"}
    rooms["Kitchen"]["furniture"].append(tv)
    with pytest.raises(ValueError, match="'on' names 'TVStand'"):
        validate_catalog(rooms=rooms)
    rooms = catalog.load_room_templates()
    del rooms["Bathroom"]["small"]["Towel"]  # variant_weights still mentions it
    with pytest.raises(ValueError, match="variant_weights for 'Towel'"):
        validate_catalog(rooms=rooms)


def test_broken_categories_raise() -> None:
    cats = dict(CATEGORIES)
    mug = cats["Mug"]
    cats["Mug"] = dataclasses.replace(mug, parts=(*mug.parts, Part("box", (0.45, 0, 0.5), (0.2, 0.2, 0.2))))
    with pytest.raises(ValueError, match="Mug part .* outside the bounding box"):
        validate_catalog(categories=cats)
    cats = dict(CATEGORIES)
    fridge = cats["Fridge"]
    cats["Fridge"] = dataclasses.replace(fridge, parts=tuple(pt for pt in fridge.parts if pt.door is None))
    with pytest.raises(ValueError, match="Fridge: openable but no door part"):
        validate_catalog(categories=cats)
    cats = dict(CATEGORIES)
    cats["Shelf"] = dataclasses.replace(cats["Shelf"], surfaces=())
    with pytest.raises(ValueError, match="Shelf: receptacle without surfaces"):
        validate_catalog(categories=cats)
    cats = dict(CATEGORIES)
    recoloured = dataclasses.replace(mug.parts[-1], color="coffee")
    cats["Mug"] = dataclasses.replace(mug, parts=(*mug.parts[:-1], recoloured))
    with pytest.raises(ValueError, match="colour role 'coffee' missing"):
        validate_catalog(categories=cats)


# -------------------------------------------------------------------------- priors


def test_priors_normalise() -> None:
    for name in PRIORS:
        c = CATEGORIES[name]
        for room in ROOM_TYPES:
            for var in (None, *[v.name for v in c.variants]):
                w = receptacle_weights(name, var, room)
                assert math.isclose(sum(w.values()), 1.0), (name, var, room)
                assert set(w) <= receptacle_types(room), (name, var, room)


def test_priors_are_spread_not_one_answer() -> None:
    # Several plausible receptacles per object; the top receptacle is not always the same
    # across rooms and variants.
    multi = [n for n, e in PRIORS.items() for by_room in e.values() for t in by_room.values() if len(t) >= 3]
    assert len(multi) >= 40
    tops = {next(iter(receptacle_weights("Mug", None, r))) for r in ROOM_TYPES[:3]}
    assert len(tops) >= 2


def test_bowl_goes_to_dining_table_else_counter() -> None:
    kitchen = ["CounterTop", "Sink", "Fridge", "Cabinet", "StoveBurner", "Microwave", "GarbageCan"]
    with_table = receptacle_weights("Bowl", "cereal", "Kitchen", present=kitchen + ["DiningTable"])
    without = receptacle_weights("Bowl", "cereal", "Kitchen", present=kitchen)
    assert next(iter(with_table)) == "DiningTable"
    assert next(iter(without)) == "CounterTop"
    assert "DiningTable" not in without
    assert math.isclose(sum(without.values()), 1.0)
    assert without["CounterTop"] > with_table["CounterTop"]


def test_present_fallback_is_uniform_when_nothing_fits() -> None:
    w = receptacle_weights("Pan", None, "Kitchen", present=["DiningTable"])
    assert set(w) == {"DiningTable", "Floor"} and math.isclose(w["Floor"], 0.5)


def test_variants_change_priors() -> None:
    def top(cat: str, var: str, room: str) -> str:
        return next(iter(receptacle_weights(cat, var, room)))

    assert top("Vase", "large", "LivingRoom") == "Floor"
    assert top("Vase", "small", "LivingRoom") != "Floor"
    assert top("Pillow", "bed", "Bedroom") == "Bed"
    bed, throw = (receptacle_weights("Pillow", v, "Bedroom")["Bed"] for v in ("bed", "throw"))
    assert bed > throw
    assert top("Statue", "sculpture", "LivingRoom") == "Floor"
    assert top("Statue", "figurine", "LivingRoom") == "Shelf"
    assert "Sink" in receptacle_weights("Towel", "hand", "Bathroom")
    assert receptacle_weights("Towel", "bath", "Bathroom").get("Bathtub", 0) > receptacle_weights(
        "Towel", "hand", "Bathroom"
    ).get("Bathtub", 0)
    assert receptacle_weights("Book", "cookbook", "Kitchen")["CounterTop"] > 0.3


def test_plausibility() -> None:
    assert not is_plausible("Mug", None, "Kitchen", "Floor")
    for rec in ("CounterTop", "DiningTable", "Shelf", "Cabinet"):
        assert is_plausible("Mug", None, "Kitchen", rec), rec
    assert not is_plausible("Mug", None, "Kitchen", "Microwave")
    assert is_plausible("Vase", "large", "LivingRoom", "Floor")
    assert not is_plausible("Vase", "small", "LivingRoom", "Floor")
    assert not is_plausible("Apple", None, "Kitchen", "GarbageCan")
    assert is_plausible("BasketBall", None, "Bedroom", "Floor")
    assert not is_plausible("Pillow", "bed", "Bedroom", "Floor")
    # Renormalising over what is present does not change the verdict for what stays.
    assert is_plausible("Mug", None, "Kitchen", "Shelf", present=["Shelf", "CounterTop"])


def test_unknown_inputs() -> None:
    with pytest.raises(KeyError):
        receptacle_weights("Fridge", None, "Kitchen")
    with pytest.raises(KeyError):
        receptacle_weights("Vase", "enormous", "Kitchen")
    # A category carried into a room it never starts in still gets a sensible answer.
    w = receptacle_weights("Pan", None, "Bathroom")
    assert set(w) <= {"Cabinet", "Sink"} and math.isclose(sum(w.values()), 1.0)


# --------------------------------------------------------------------------- rooms


def test_room_templates() -> None:
    assert set(ROOM_TEMPLATES) == set(ROOM_TYPES)
    must = {
        "Kitchen": {"CounterTop", "Fridge", "Sink", "StoveBurner", "Cabinet", "Microwave", "GarbageCan"},
        "LivingRoom": {"Sofa", "CoffeeTable", "TVStand", "Television"},
        "Bedroom": {"Bed", "SideTable", "Dresser"},
        "Bathroom": {"Toilet", "Sink", "Bathtub", "TowelHolder", "ToiletPaperHanger", "GarbageCan", "Mirror"},
    }
    for room, tpl in ROOM_TEMPLATES.items():
        required = {f["type"] for f in tpl["furniture"] if f["required"]}
        assert must[room] <= required, room
        assert len(tpl["small"]) >= 10
        for cat in tpl["small"]:
            assert math.isclose(sum(variant_weights(cat, room).values()), 1.0)


def test_furniture_footprint_fits_room() -> None:
    # Floor-standing furniture at mean size: the required pieces at their maximum count
    # cover at most half of the smallest room of the type, and everything at its maximum
    # count at most half of a mid-sized one (the generator drops optional pieces that do
    # not fit).
    for room, tpl in ROOM_TEMPLATES.items():
        (x0, x1), (y0, y1) = tpl["size"]
        required = everything = 0.0
        for f in tpl["furniture"]:
            c = CATEGORIES[f["type"]]
            if c.kind != "furniture" or f.get("on") or c.placement == "wall_mounted":
                continue
            lk = look(c.name, f.get("variant"))
            sx, sy = ((a + b) / 2 for a, b in list(zip(lk.size_min, lk.size_max))[:2])
            everything += f["count"][1] * sx * sy
            required += f["count"][1] * sx * sy if f["required"] else 0.0
        assert required <= 0.5 * x0 * y0, (room, required, x0 * y0)
        assert everything <= 0.5 * (x0 + x1) * (y0 + y1) / 4, (room, everything)


# ------------------------------------------------------------------ PyBullet builds


def _lathe_mesh(
    profile: tuple[tuple[float, float], ...], radius: float, height: float, segments: int = 16
) -> tuple[list[list[float]], list[int]]:
    verts: list[list[float]] = []
    for r, z in profile:
        for k in range(segments):
            a = 2 * math.pi * k / segments
            verts.append([r * radius * math.cos(a), r * radius * math.sin(a), (z - 0.5) * height])
    idx: list[int] = []
    for i in range(len(profile) - 1):
        for k in range(segments):
            a, b = i * segments + k, i * segments + (k + 1) % segments
            c, d = a + segments, b + segments
            idx += [a, b, d, a, d, c]
    return verts, idx


def build_body(
    client: int, name: str, variant: str | None, size: tuple[float, float, float], palette: dict[str, str]
) -> int:
    """A minimal recipe builder: one visual (+ collision) shape per part, all fixed to a base."""
    sx, sy, sz = size
    vis, col, pos = [], [], []
    for part in look(name, variant).parts:
        hexcol = part.color if part.color.startswith("#") else palette[part.color]
        rgba = [int(hexcol[i : i + 2], 16) / 255 for i in (1, 3, 5)] + [1.0]
        e = part.extent
        if part.shape == "box":
            half = [e[0] * sx / 2, e[1] * sy / 2, e[2] * sz / 2]
            v = p.createVisualShape(p.GEOM_BOX, halfExtents=half, rgbaColor=rgba, physicsClientId=client)
            cs = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=client)
        elif part.shape == "cylinder":
            r, h = e[0] * sx / 2, e[2] * sz
            v = p.createVisualShape(
                p.GEOM_CYLINDER, radius=r, length=h, rgbaColor=rgba, physicsClientId=client
            )
            cs = p.createCollisionShape(p.GEOM_CYLINDER, radius=r, height=h, physicsClientId=client)
        elif part.shape == "sphere":
            r = e[0] * sx / 2
            v = p.createVisualShape(p.GEOM_SPHERE, radius=r, rgbaColor=rgba, physicsClientId=client)
            cs = p.createCollisionShape(p.GEOM_SPHERE, radius=r, physicsClientId=client)
        else:
            verts, idx = _lathe_mesh(part.profile, e[0] * sx / 2, e[2] * sz)
            v = p.createVisualShape(
                p.GEOM_MESH, vertices=verts, indices=idx, rgbaColor=rgba, physicsClientId=client
            )
            cs = p.createCollisionShape(p.GEOM_MESH, vertices=verts, physicsClientId=client)
        assert v >= 0 and cs >= 0, (name, variant, part)
        vis.append(v)
        col.append(cs if part.collide else -1)
        pos.append([part.center[0] * sx, part.center[1] * sy, part.center[2] * sz])
    n = len(vis)
    body = p.createMultiBody(
        baseMass=0,
        basePosition=[0, 0, 0],
        linkMasses=[0.0] * n,
        linkCollisionShapeIndices=col,
        linkVisualShapeIndices=vis,
        linkPositions=pos,
        linkOrientations=[[0, 0, 0, 1]] * n,
        linkInertialFramePositions=[[0, 0, 0]] * n,
        linkInertialFrameOrientations=[[0, 0, 0, 1]] * n,
        linkParentIndices=[0] * n,
        linkJointTypes=[p.JOINT_FIXED] * n,
        linkJointAxis=[[0, 0, 1]] * n,
        physicsClientId=client,
    )
    assert body >= 0, name
    return body


def test_every_recipe_builds_in_pybullet() -> None:
    client = p.connect(p.DIRECT)
    try:
        rng = random.Random(1)
        n = 0
        for name, c in CATEGORIES.items():
            for var in (None, *[v.name for v in c.variants]):
                size = sample_size(name, var, rng)
                palette = rng.choice(look(name, var).palettes)
                body = build_body(client, name, var, size, palette)
                lo, hi = p.getAABB(body, -1, physicsClientId=client)
                assert p.getNumJoints(body, physicsClientId=client) == len(look(name, var).parts)
                p.removeBody(body, physicsClientId=client)
                n += 1
        assert n >= len(CATEGORIES)
    finally:
        p.disconnect(client)
