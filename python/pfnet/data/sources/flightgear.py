"""FlightGear's models: ``AI/Aircraft`` and ``Scenery/Models`` of a FlightGear data tree.

Debian's ``flightgear-data-ai`` installs ``/usr/share/games/flightgear/AI/Aircraft`` (113
aircraft types, 223 ``.ac`` files: the meshes and their light sub-models) and
``flightgear-data-base`` ``Scenery/Models`` (2,193 ``.ac`` files in folders such as
``Aircraft``, ``Maritime``, ``Transport``, ``Airport``, ``Residential``). Give the data tree
(``/usr/share/games/flightgear``) or any folder of the same layout.

Categories come from the folder (``Scenery/Models/Maritime`` is ``ship``, ``Residential``
``building``...) and then from the file name (:data:`CATEGORY_RULES`; a helicopter among the
aircraft, a bus among the transport models). Left out, and counted by reason
(:data:`EXCLUDE_RULES`): light, strobe and flare sub-models, refuelling booms, drop tanks and
other aircraft parts, multi-vehicle ``services`` groups, trailers, light cones, the
``Effects`` folder (clouds, smoke) and ``Trees`` (crossed billboards, not surfaces). What no
rule names gets ``other``. Files are y-up (see :mod:`pfnet.data.sources.ac3d_trees`).
Licence: GPL-2+ (``/usr/share/doc/flightgear-data-*/copyright``).
"""

from __future__ import annotations

from pathlib import Path

from pfnet.data.sources import Scan
from pfnet.data.sources.ac3d_trees import Found, compile_rules, first_match, make_scan
from pfnet.errors import DataError

__all__ = ["CATEGORY_RULES", "DEFAULT_PATH", "EXCLUDE_RULES", "categorize", "looks_like", "scan"]

DEFAULT_PATH = Path("/usr/share/games/flightgear")
"""Where Debian's ``flightgear-data-*`` packages install the data tree."""

LICENSE = {
    "source": "flightgear",
    "catalogue": "FlightGear AI aircraft and scenery models (flightgear-data-ai, -base)",
    "license": "GPL-2+",
    "provider": "The FlightGear project, www.flightgear.org (model authors: see "
    "/usr/share/doc/flightgear-data-ai/copyright and flightgear-data-base/copyright)",
}

# Where the walk looks, relative to the data tree.
ROOTS = ("AI/Aircraft", "Scenery/Models")

_AIRCRAFT = ("AI/Aircraft", "Scenery/Models/Aircraft")
_VEHICLES = ("Scenery/Models/Airport/Vehicle", "Scenery/Models/Airport/Pushback")
# (reason, regex on the file name without suffix, folders it applies to; () = everywhere)
EXCLUDE_RULES: tuple[tuple[str, str, tuple[str, ...]], ...] = (
    ("effects", r".", ("Scenery/Models/Effects",)),
    ("billboard_tree", r".", ("Scenery/Models/Trees",)),
    ("light_cone", r"light-?cone", ()),
    (
        "light",
        r"(white|green|red)light|^light[-_]|^flash|blueflash|strobe|^beacon$|^nav(l|r|back|"
        r"lights)?$|flare|^toggle|landinglights|^lights?$|procedural_light|taxi-light|"
        r"landing-light",
        (*_AIRCRAFT, *_VEHICLES, "AI"),
    ),
    (
        "aircraft_part",
        r"refuel|probe|droptank|^tank$|^wheels$|exhaust|banner|^bomb|^taxi$",
        ("AI/Aircraft",),
    ),
    ("services_group", r"services|group|^vehicules_|^traffic-ba|^caisses", ()),
    ("trailer", r"trailer", ()),
)

_HELICOPTER = (
    r"heli(?!pad)|copter|mi-8|mi-6|mil-mi|ec-?1[34]5|r44|jetranger|superfrelon|lynx|"
    r"hh-60|esquilo|^dauphin"
)
# (category, regex on the file name) per folder; the first match wins, else the default
CATEGORY_RULES: dict[str, tuple[str, tuple[tuple[str, str], ...]]] = {
    "AI/Aircraft": ("airplane", (("helicopter", _HELICOPTER), ("other", r"balloon"))),
    "Scenery/Models/Aircraft": (
        "airplane",
        (("helicopter", _HELICOPTER), ("other", r"arff-trainer")),
    ),
    "Scenery/Models/Maritime/Misc": (
        "other",
        (("ship", r"boat|vessel|raft"),),
    ),
    "Scenery/Models/Maritime": (
        "ship",
        (
            (
                "other",
                r"lock1|lighthouse|^dam$|ponton|crane|oberfeuer|pier|shipyard",
            ),
        ),
    ),
    "Scenery/Models/Airport/Vehicle": (
        "truck",
        (
            ("helicopter", _HELICOPTER),
            ("bus", r"bus"),
            ("car", r"hatchback|follow|pickup|rover|sprinter|van-|^van|fourgon|boxvan"),
            ("other", r"cart|chariot|dolly|contain|gpu|stairs|passerelle|elevator|winch"),
        ),
    ),
    "Scenery/Models/Airport/Pushback": ("truck", ()),
    "Scenery/Models/Airport": (
        "other",
        (
            ("lamp", r"lamp|light.?pole|lightmast|eclairage"),
            (
                "building",
                r"hang[ae]r|tower|terminal|office|building|bldg|admin|station|house|garage|"
                r"hall|fbo|club|warehouse|^tour|twr|barn|cahute|maison|ecole|contr|aeroclub|"
                r"rotonde|^tw_|module",
            ),
        ),
    ),
    "Scenery/Models/Transport": (
        "other",
        (
            ("ship", r"srn4"),
            (
                "train",
                r"train|metro|tram|coach|locomotive|ice3|hitachi|class_66|switcher|^lint|"
                r"diesel|flatcar|wagon|tender",
            ),
            ("bus", r"bus"),
            (
                "truck",
                r"truck|bulldozer|dump|grader|roller|digger|forklift|tractor|fc6m1|motorhome",
            ),
            (
                "car",
                r"camry|camaro|hatchback|vw|golf|jetta|passat|honda|volvo|bmw|mazda|polic|"
                r"hummer|pickup|dodgeram|van|paramedic|voyager|taxi",
            ),
        ),
    ),
    "Scenery/Models/Military": (
        "building",
        (
            ("airplane", r"^f-16|^kc10"),
            ("car", r"humvee"),
            ("truck", r"truck|tractor"),
            ("other", r"missile|launcher|sa-2|bloodhound|guard|bak-12|gantry|skijump|tank"),
        ),
    ),
    "Scenery/Models/Residential": ("building", (("other", r"caravan|transf"),)),
    "Scenery/Models/Commercial": ("building", (("other", r"fan|tecalemit"),)),
    "Scenery/Models/Industrial": ("building", (("other", r"heap|flare"),)),
    "Scenery/Models/Agriculture": ("building", (("other", r"bale|frame|tunnel"),)),
    "": (
        "other",
        (
            ("lamp", r"lamp"),
            ("person", r"worker|pilot\d|^armedguard"),
            ("building", r"church|castle|chapel|kapelle|monument|station|house|hut$"),
        ),
    ),
}

_EXCLUDE = tuple(
    (reason, compile_rules([("", pattern)])[0][1], folders)
    for reason, pattern, folders in EXCLUDE_RULES
)
_CATEGORIES = {
    folder: (default, compile_rules(rules)) for folder, (default, rules) in CATEGORY_RULES.items()
}


def _under(relative: str, folder: str) -> bool:
    return folder == "" or relative == folder or relative.startswith(folder + "/")


def categorize(relative: str) -> tuple[str | None, str]:
    """The category of a file of the tree, or why it is left out.

    Args:
        relative: The file's path relative to the data tree (``AI/Aircraft/A320/...``).

    Returns:
        ``(category, "")`` or ``(None, reason)``.
    """
    path = Path(relative)
    stem = path.stem.lower()
    folder = path.parent.as_posix()
    parts = {p.lower() for p in path.parent.parts}
    for reason, pattern, folders in _EXCLUDE:
        if (not folders or any(_under(folder, f) for f in folders)) and pattern.search(stem):
            return None, reason
    if _under(folder, "AI/Aircraft") and parts & {"light", "lights"}:
        return None, "light"
    # the most specific folder with rules wins
    for rule_folder in sorted(_CATEGORIES, key=len, reverse=True):
        if _under(folder, rule_folder):
            default, rules = _CATEGORIES[rule_folder]
            return first_match(stem, rules) or default, ""
    return "other", ""


def looks_like(source: Path) -> bool:
    """Whether ``source`` is a FlightGear data tree (has ``AI/Aircraft`` or ``Scenery/Models``)."""
    return source.is_dir() and any((source / root).is_dir() for root in ROOTS)


def scan(source: Path) -> Scan:
    """Find the models of a FlightGear data tree.

    Args:
        source: The data tree (holding ``AI/Aircraft`` and/or ``Scenery/Models``).

    Returns:
        The scan: one item per kept ``.ac`` file, the files left out counted by reason.

    Raises:
        DataError: Neither folder is there, or no model is found.
    """
    if not looks_like(source):
        raise DataError(f"{source}: not a FlightGear data tree (no {' or '.join(ROOTS)} folder)")
    found: list[Found] = []
    for root in ROOTS:
        if not (source / root).is_dir():
            continue
        for path in sorted((source / root).rglob("*")):
            if path.suffix.lower() != ".ac" or not path.is_file():
                continue
            relative = path.relative_to(source).as_posix()
            category, reason = categorize(relative)
            found.append(Found(path, relative, category, reason))
    return make_scan("flightgear", found, [LICENSE])
