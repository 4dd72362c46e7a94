"""Parameters of a procedural character head and the archetypes the prompt picks from.

Lengths are in "head units" (cranium radius about 1) before the mesh is normalised to the
canonical frame. Angles are degrees. Colours are RGB in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass, replace

RGB = tuple[float, float, float]


@dataclass
class CharacterParams:
    archetype: str = "cartoon"  # archetype name (recorded in the manifest)
    head_radii: tuple[float, float, float] = (1.0, 0.95, 0.95)  # cranium semi-axes x, y, z
    squareness: float = 2.0  # superellipsoid exponent of the cranium: 2 = ellipsoid, 5+ = boxy (robot)
    cranium_lift: float = 0.0  # extra height at the top of the cranium (alien, bug)
    snout_length: float = 0.0  # how far the muzzle is pulled forward (0 = flat face)
    snout_angle: float = 38.0  # half-angle of the muzzle's footprint on the head
    snout_taper: float = 0.35  # muzzle narrows toward its tip (0 = straight)
    snout_drop: float = 0.25  # slope of the muzzle axis below horizontal
    mouth_height: float = -0.38  # mouth line y on a flat face (fraction of the head height)
    mouth_width: float = 0.36  # half width of the mouth
    jaw_size: float = 1.0  # bulk of the lower jaw
    eye_size: float = 0.2  # eyeball radius
    eye_azimuth: float = 27.0  # eyes' angle from the midline seen from above
    eye_elevation: float = 12.0  # eyes' angle above the head centre
    eye_forward: float = 0.75  # eyes look along +Z (1) or along the head normal (0)
    pupil: str = "round"  # round | slit | compound | glow
    iris_color: RGB = (0.35, 0.22, 0.1)
    ear: str = "none"  # none | pointy | round | long | floppy | side | human | leaf | antenna | tuft | bolt
    ear_size: float = 0.5  # ear height
    ear_width: float = 0.5  # ear width relative to its height
    ear_azimuth: float = 40.0  # ear base angle from the midline
    ear_elevation: float = 45.0  # ear base angle above the head centre
    ear_tilt: float = 20.0  # outward tilt of the ear axis from vertical
    horn: str = "none"  # none | antlers | horns | spikes | antenna
    horn_size: float = 0.6
    nose: str = "button"  # none | button | human | beak
    nose_size: float = 0.1
    teeth: str = "flat"  # flat | sharp | fangs | buck
    extras: tuple[str, ...] = ()  # fin | tears | petals | hair | blush | gills
    base_color: RGB = (0.85, 0.7, 0.55)
    secondary_color: RGB = (0.97, 0.95, 0.9)
    secondary: str = "none"  # where the secondary colour goes: none | muzzle | belly | blaze | face | top
    pattern: str = "none"  # none | stripes | spots | panels
    pattern_color: RGB = (0.2, 0.15, 0.1)
    ear_inner_color: RGB = (0.95, 0.7, 0.7)
    ear_tip_color: RGB | None = None
    nose_color: RGB = (0.08, 0.06, 0.06)
    lip_color: RGB | None = None  # None: a darker shade of the skin
    brow_color: RGB | None = None  # None: a darker shade of the skin
    horn_color: RGB = (0.85, 0.78, 0.62)
    extra_color: RGB = (1.0, 0.55, 0.75)  # petals, fins, antenna balls
    hair_color: RGB = (0.3, 0.18, 0.1)
    brow_size: float = 1.0


def _p(**kw) -> CharacterParams:
    return CharacterParams(**kw)


ORANGE = (0.93, 0.47, 0.15)
WHITE = (0.97, 0.96, 0.93)

ARCHETYPES: dict[str, CharacterParams] = {
    "fox": _p(archetype="fox", head_radii=(0.95, 0.88, 0.9), snout_length=0.75, snout_taper=0.55, snout_angle=36,
              mouth_width=0.2, ear="pointy", ear_size=0.75, ear_width=0.55, ear_azimuth=38, ear_elevation=50,
              ear_tilt=18, base_color=ORANGE, secondary="muzzle", ear_inner_color=WHITE,
              ear_tip_color=(0.12, 0.08, 0.06), iris_color=(0.75, 0.45, 0.05), eye_size=0.19, teeth="fangs"),
    "dog": _p(archetype="dog", head_radii=(1.0, 0.92, 0.92), snout_length=0.5, snout_taper=0.25, snout_angle=40,
              mouth_width=0.26, ear="pointy", ear_size=0.62, ear_width=0.75, ear_azimuth=42, ear_elevation=47,
              ear_tilt=22, base_color=(0.86, 0.55, 0.22), secondary="blaze", ear_inner_color=(0.95, 0.75, 0.7),
              iris_color=(0.3, 0.17, 0.06), eye_size=0.2, teeth="fangs"),
    "cat": _p(archetype="cat", head_radii=(1.05, 0.92, 0.92), snout_length=0.18, snout_taper=0.2, snout_angle=34,
              mouth_width=0.22, mouth_height=-0.4, ear="pointy", ear_size=0.55, ear_width=0.8, ear_azimuth=36,
              ear_elevation=50, ear_tilt=15, base_color=(0.55, 0.55, 0.58), secondary="muzzle", pattern="stripes",
              pattern_color=(0.3, 0.3, 0.33), iris_color=(0.35, 0.75, 0.2), pupil="slit", nose_color=(0.9, 0.5, 0.55),
              nose_size=0.07, teeth="fangs", eye_size=0.22),
    "deer": _p(archetype="deer", head_radii=(0.85, 0.9, 0.9), snout_length=0.65, snout_taper=0.3, snout_angle=36,
               snout_drop=0.4, mouth_width=0.22, ear="side", ear_size=0.55, ear_width=0.5, ear_azimuth=60,
               ear_elevation=35, ear_tilt=65, horn="antlers", horn_size=0.9, base_color=(0.62, 0.4, 0.22),
               secondary="muzzle", pattern="spots", pattern_color=(0.93, 0.88, 0.8), ear_inner_color=(0.95, 0.85, 0.8),
               iris_color=(0.2, 0.12, 0.06), eye_size=0.2, eye_azimuth=32),
    "bear": _p(archetype="bear", head_radii=(1.08, 0.98, 0.95), snout_length=0.35, snout_taper=0.15, snout_angle=38,
               mouth_width=0.26, ear="round", ear_size=0.36, ear_width=1.0, ear_azimuth=45, ear_elevation=52,
               ear_tilt=20, base_color=(0.5, 0.32, 0.18), secondary="muzzle", secondary_color=(0.85, 0.72, 0.55),
               ear_inner_color=(0.8, 0.62, 0.45), iris_color=(0.15, 0.08, 0.03), eye_size=0.17, nose_size=0.13),
    "rabbit": _p(archetype="rabbit", head_radii=(0.95, 0.92, 0.92), snout_length=0.2, snout_taper=0.2,
                 mouth_width=0.2, ear="long", ear_size=1.15, ear_width=0.38, ear_azimuth=22, ear_elevation=62,
                 ear_tilt=8, base_color=(0.93, 0.92, 0.92), secondary="muzzle", secondary_color=(1.0, 1.0, 1.0),
                 ear_inner_color=(0.98, 0.65, 0.72), nose_color=(0.95, 0.5, 0.6), nose_size=0.07, teeth="buck",
                 iris_color=(0.55, 0.2, 0.3), eye_size=0.21),
    "shark": _p(archetype="shark", head_radii=(0.82, 0.8, 1.05), snout_length=0.75, snout_taper=0.35, snout_angle=48,
                snout_drop=-0.05, mouth_width=0.42, jaw_size=1.2, eye_size=0.12, eye_azimuth=58, eye_elevation=12,
                eye_forward=0.2, pupil="round", iris_color=(0.03, 0.03, 0.05), ear="none", nose="none",
                teeth="sharp", extras=("fin", "gills"), base_color=(0.45, 0.55, 0.66), secondary="belly",
                secondary_color=(0.95, 0.95, 0.95), extra_color=(0.42, 0.52, 0.63), brow_size=0.0),
    "dinosaur": _p(archetype="dinosaur", head_radii=(0.8, 0.85, 0.95), snout_length=0.85, snout_taper=0.3,
                   snout_angle=42, snout_drop=0.1, mouth_width=0.3, jaw_size=1.2, eye_size=0.14, eye_azimuth=40,
                   eye_elevation=22, eye_forward=0.4, pupil="slit", iris_color=(0.95, 0.75, 0.1), ear="none",
                   nose="none", teeth="sharp", horn="spikes", horn_size=0.5, base_color=(0.35, 0.45, 0.3),
                   secondary="belly", secondary_color=(0.8, 0.78, 0.6), pattern="stripes",
                   pattern_color=(0.18, 0.22, 0.15), horn_color=(0.3, 0.32, 0.28)),
    "bird": _p(archetype="bird", head_radii=(1.0, 1.0, 0.92), mouth_width=0.14, mouth_height=-0.42, eye_size=0.27,
               eye_azimuth=28, eye_elevation=10, iris_color=(0.95, 0.65, 0.05), ear="tuft", ear_size=0.45,
               ear_width=0.5, ear_azimuth=40, ear_elevation=62, ear_tilt=25, nose="beak", nose_size=0.22,
               base_color=(0.55, 0.4, 0.28), secondary="face", secondary_color=(0.92, 0.85, 0.72),
               nose_color=(0.95, 0.65, 0.15), teeth="flat", brow_size=1.2),
    "frog": _p(archetype="frog", head_radii=(1.15, 0.75, 0.9), mouth_height=-0.2, mouth_width=0.62, eye_size=0.25,
               eye_azimuth=34, eye_elevation=48, eye_forward=0.5, iris_color=(0.85, 0.65, 0.1), ear="none",
               nose="none", base_color=(0.35, 0.7, 0.25), secondary="belly", secondary_color=(0.85, 0.9, 0.6),
               pattern="spots", pattern_color=(0.2, 0.45, 0.15), lip_color=(0.25, 0.5, 0.18), brow_size=0.0),
    "robot": _p(archetype="robot", head_radii=(0.95, 0.9, 0.85), squareness=6.0, mouth_width=0.4,
                mouth_height=-0.42, eye_size=0.2, eye_azimuth=26, eye_elevation=10, eye_forward=1.0, pupil="glow",
                iris_color=(0.2, 0.9, 1.0), ear="bolt", ear_size=0.3, ear_width=1.0, ear_azimuth=88,
                ear_elevation=5, ear_tilt=90, horn="antenna", horn_size=0.5, nose="none",
                base_color=(0.68, 0.7, 0.74), pattern="panels", pattern_color=(0.45, 0.47, 0.52),
                lip_color=(0.35, 0.36, 0.4), brow_color=(0.3, 0.31, 0.35), extra_color=(0.95, 0.2, 0.15)),
    "alien": _p(archetype="alien", head_radii=(0.92, 1.0, 0.88), cranium_lift=0.35, mouth_width=0.2,
                mouth_height=-0.52, jaw_size=0.7, eye_size=0.27, eye_azimuth=30, eye_elevation=2, pupil="compound",
                iris_color=(0.04, 0.04, 0.06), ear="antenna", ear_size=0.8, ear_azimuth=25, ear_elevation=65,
                ear_tilt=20, nose="none", base_color=(0.55, 0.85, 0.45), extra_color=(0.9, 0.95, 0.3),
                brow_size=0.0),
    "bug": _p(archetype="bug", head_radii=(1.0, 0.9, 0.9), cranium_lift=0.1, mouth_width=0.22, mouth_height=-0.45,
              snout_length=0.15, eye_size=0.32, eye_azimuth=42, eye_elevation=18, eye_forward=0.3,
              pupil="compound", iris_color=(0.55, 0.05, 0.08), ear="antenna", ear_size=0.95, ear_azimuth=18,
              ear_elevation=60, ear_tilt=30, nose="none", teeth="fangs", base_color=(0.2, 0.55, 0.3),
              pattern="top", pattern_color=(0.1, 0.3, 0.15), extra_color=(0.15, 0.3, 0.18), brow_size=0.0),
    "plant": _p(archetype="plant", head_radii=(0.95, 0.95, 0.85), mouth_width=0.28, eye_size=0.19,
                iris_color=(0.25, 0.15, 0.05), ear="leaf", ear_size=0.75, ear_width=0.45, ear_azimuth=25,
                ear_elevation=70, ear_tilt=40, nose="none", extras=("petals",), base_color=(0.98, 0.82, 0.25),
                secondary="none", extra_color=(0.95, 0.4, 0.55), ear_inner_color=(0.3, 0.7, 0.25),
                brow_color=(0.55, 0.35, 0.1)),
    "human": _p(archetype="human", head_radii=(0.88, 1.0, 0.92), mouth_width=0.26, mouth_height=-0.45,
                eye_size=0.18, eye_azimuth=24, eye_elevation=8, iris_color=(0.25, 0.45, 0.7), ear="human",
                ear_size=0.32, ear_width=0.65, ear_azimuth=90, ear_elevation=0, ear_tilt=0, nose="human",
                nose_size=0.12, extras=("hair", "blush"), base_color=(0.96, 0.78, 0.65),
                lip_color=(0.82, 0.4, 0.4), hair_color=(0.35, 0.2, 0.1)),
    "cartoon": _p(archetype="cartoon", head_radii=(1.0, 0.95, 0.95), mouth_width=0.3, eye_size=0.22,
                  iris_color=(0.3, 0.5, 0.2), ear="round", ear_size=0.35, ear_width=0.9, ear_azimuth=70,
                  ear_elevation=35, ear_tilt=55, base_color=(0.6, 0.72, 0.95), nose="button",
                  nose_color=(0.95, 0.45, 0.45), extras=("blush",)),
}

# Words that select an archetype (first match in the prompt wins), with per-word tweaks.
ARCHETYPE_WORDS: dict[str, tuple[str, dict]] = {
    "fox": ("fox", {}), "vixen": ("fox", {}), "wolf": ("fox", {"base_color": (0.55, 0.57, 0.6)}),
    "corgi": ("dog", {}), "dog": ("dog", {}), "puppy": ("dog", {"eye_size": 0.23}),
    "doggy": ("dog", {}), "doggo": ("dog", {}),
    "beagle": ("dog", {"ear": "floppy", "ear_size": 0.7, "ear_width": 0.6}),
    "cat": ("cat", {}), "kitten": ("cat", {"eye_size": 0.24}), "kitty": ("cat", {}),
    "tiger": ("cat", {"base_color": ORANGE, "pattern_color": (0.1, 0.08, 0.06), "snout_length": 0.3}),
    "lion": ("cat", {"base_color": (0.85, 0.65, 0.3), "pattern": "none", "ear": "round", "ear_size": 0.3}),
    "deer": ("deer", {}), "reindeer": ("deer", {}), "fawn": ("deer", {"horn": "none"}), "elk": ("deer", {}),
    "moose": ("deer", {"snout_length": 0.8}), "stag": ("deer", {}),
    "bear": ("bear", {}), "teddy": ("bear", {}), "panda": ("bear", {
        "base_color": (0.96, 0.96, 0.94), "secondary": "none", "ear_inner_color": (0.1, 0.1, 0.1),
        "iris_color": (0.05, 0.05, 0.05)}),
    "rabbit": ("rabbit", {}), "bunny": ("rabbit", {}), "hare": ("rabbit", {"base_color": (0.7, 0.55, 0.4)}),
    "shark": ("shark", {}), "fish": ("shark", {"teeth": "flat", "base_color": (0.95, 0.55, 0.2),
                                               "secondary_color": (0.98, 0.9, 0.7)}),
    "dolphin": ("shark", {"teeth": "flat", "base_color": (0.5, 0.6, 0.72)}),
    "dinosaur": ("dinosaur", {}), "dino": ("dinosaur", {}), "raptor": ("dinosaur", {}),
    "velociraptor": ("dinosaur", {}),
    "indoraptor": ("dinosaur", {"base_color": (0.16, 0.16, 0.17), "pattern_color": (0.75, 0.6, 0.2),
                                "secondary_color": (0.3, 0.3, 0.3), "iris_color": (0.95, 0.8, 0.1)}),
    "trex": ("dinosaur", {"jaw_size": 1.4}), "t-rex": ("dinosaur", {"jaw_size": 1.4}),
    "dragon": ("dinosaur", {"horn": "horns", "base_color": (0.7, 0.15, 0.15)}),
    "lizard": ("dinosaur", {"horn": "none"}), "crocodile": ("dinosaur", {"snout_length": 1.1, "horn": "spikes"}),
    "bird": ("bird", {}), "owl": ("bird", {}), "chick": ("bird", {"base_color": (1.0, 0.85, 0.2), "ear": "none"}),
    "parrot": ("bird", {"base_color": (0.2, 0.7, 0.3), "ear": "none"}),
    "penguin": ("bird", {"base_color": (0.12, 0.12, 0.15), "ear": "none", "secondary_color": WHITE}),
    "frog": ("frog", {}), "toad": ("frog", {"base_color": (0.5, 0.5, 0.25)}),
    "robot": ("robot", {}), "android": ("robot", {}), "cyborg": ("robot", {}), "mech": ("robot", {}), "bot": ("robot", {}),
    "alien": ("alien", {}), "martian": ("alien", {}), "extraterrestrial": ("alien", {}), "ufo": ("alien", {}),
    "bug": ("bug", {}), "insect": ("bug", {}), "beetle": ("bug", {}), "ant": ("bug", {"base_color": (0.55, 0.15, 0.1)}),
    "bee": ("bug", {"base_color": (0.98, 0.8, 0.15), "pattern": "stripes", "pattern_color": (0.1, 0.08, 0.05)}),
    "fly": ("bug", {}), "ladybug": ("bug", {"base_color": (0.85, 0.1, 0.1), "pattern": "spots",
                                            "pattern_color": (0.05, 0.05, 0.05)}),
    "plant": ("plant", {}), "flower": ("plant", {}), "sunflower": ("plant", {"extra_color": (0.98, 0.75, 0.1),
                                                                            "base_color": (0.45, 0.3, 0.12)}),
    "rose": ("plant", {"extra_color": (0.85, 0.1, 0.2)}), "daisy": ("plant", {"extra_color": WHITE}),
    "cactus": ("plant", {"base_color": (0.3, 0.62, 0.3), "extras": (), "horn": "spikes", "horn_size": 0.25}),
    "tree": ("plant", {"base_color": (0.5, 0.35, 0.2), "extras": ()}),
    "human": ("human", {}), "man": ("human", {}), "woman": ("human", {}), "boy": ("human", {}),
    "girl": ("human", {}), "person": ("human", {}), "kid": ("human", {}), "child": ("human", {}),
    "baby": ("human", {"eye_size": 0.2, "extras": ("blush",)}), "face": ("human", {}),
    "cryinghead": ("human", {"extras": ("hair", "tears", "blush")}),
    "clown": ("human", {"nose": "button", "nose_color": (0.9, 0.1, 0.1)}),
}


def archetype_params(name: str, **overrides) -> CharacterParams:
    """A copy of an archetype's defaults with ``overrides`` applied."""
    return replace(ARCHETYPES[name], **overrides)


ARCHETYPE_NAMES = sorted(ARCHETYPES)
