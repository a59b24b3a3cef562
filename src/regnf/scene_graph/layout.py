"""Where everything lives: prim paths, attribute names and files relative to the stage."""

from __future__ import annotations

import re

WORLD = "/World"
SCENE = "/World/Scene"
INSTANCES = "/World/Instances"
PROXY = "Proxy"
"""Name of the proxy mesh child of every field prim."""
SOURCE = "Source"
"""Name of a library object's source mesh (render purpose) when it was distilled from one."""
LOOKS = "Looks"
"""Scope of a library object's materials."""
EDITED = "Edited"
"""Name of the scene's mesh less the instances' removal regions (render purpose), under /World/Scene."""
VARIANT_SET = "libraryObject"
"""The slot's VariantSet: one variant per library object of its class."""
LABEL_INSTANCE = "class"
"""Instance name of ``SemanticsLabelsAPI`` carrying the semantic class."""
LABEL_NAME = "name"
"""Instance name of ``SemanticsLabelsAPI`` carrying the library object's name (on library objects)."""
COLLIDER_APPROXIMATION = "convexHull"
"""``physics:approximation`` of every library object's collider."""

STAGE_SUFFIXES = (".usda", ".usdc")
"""Suffixes of a writable stage (export also makes .usdz, a package that is not edited)."""

ROLE_LIBRARY = "libraryObject"
"""``customLayerData["regnf"]["role"]`` of a library object's asset layer."""
ROLE_SLOT = "slot"
"""``customLayerData["regnf"]["role"]`` of a class's slot layer."""

FIELDS_DIR = "fields"
LIBRARY_DIR = "library"
SLOTS_DIR = "slots"
SCENE_CHECKPOINT = "fields/scene_field.safetensors"
"""The scene field's checkpoint, relative to the stage."""

# Attributes of a field prim (scene or library object).
A_CHECKPOINT = "regnf:field:checkpoint"
A_TO_WORLD = "regnf:field:toWorld"
A_BOUNDS = "regnf:field:bounds"
A_NAME = "regnf:field:name"
A_SYM_AXIS = "regnf:field:symmetryAxis"
A_SYM_ORDER = "regnf:field:symmetryOrder"
A_FIELD_PROVENANCE = "regnf:field:provenance"
A_SLOT_CLASS = "regnf:slot:class"

# Attributes of an instance prim.
A_OBJECT_TO_SCENE = "regnf:objectToScene"
R = "regnf:registration:"
A_METHOD = R + "method"
A_CONFIDENCE = R + "confidence"
A_ACCEPTED = R + "accepted"
A_FORCED = R + "forced"
A_REG_LIBRARY = R + "libraryName"
A_SCENE_TO_LIBRARY = R + "sceneToLibrary"
A_LOSSES = R + "losses:"
A_TIMINGS = R + "timings:"
A_THRESHOLDS = R + "thresholds:"
A_BOX_CENTER = R + "proposal:center"
A_BOX_HALF = R + "proposal:halfExtents"
A_BOX_ROTATION = R + "proposal:rotation"
A_DISCOVERY = R + "discovery"
"""JSON text: how discovery found the instance (absent when the registration was given a box)."""
A_WARNINGS = R + "warnings"
"""Text, one warning a line: what the registration warned of (absent when nothing)."""

KEY_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
"""Keys of losses / timings / thresholds: they become attribute name parts."""


def library_layer(name: str) -> str:
    """Asset layer of a library object, relative to the stage."""
    return f"{LIBRARY_DIR}/{name}.usda"


def library_checkpoint(name: str) -> str:
    """Checkpoint of a library object, relative to the stage."""
    return f"{FIELDS_DIR}/{name}.safetensors"


def library_texture(name: str) -> str:
    """Base-colour texture of a library object's source mesh, relative to the stage."""
    return f"{LIBRARY_DIR}/textures/{name}.png"


def slot_layer(label: str) -> str:
    """Slot asset of a class, relative to the stage."""
    return f"{SLOTS_DIR}/{label}.usda"


def prim_name(name: str) -> str:
    """A valid prim name for a library name (``fc-nop`` -> ``fc_nop``)."""
    out = re.sub(r"[^A-Za-z0-9_]", "_", name)
    return out if re.match(r"^[A-Za-z_]", out) else f"_{out}"


def instance_path(instance_id: str) -> str:
    return f"{INSTANCES}/{instance_id}"
