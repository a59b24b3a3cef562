"""The USD scene graph: the scene field, the library and every registered instance.

A :class:`ComposedScene` is written to a stage (``write_stage``, ``new_stage``,
``add_instance``, ``add_instance_from_registration``), read back (``read_stage``), swapped
per instance by a layer of variant selections (``make_replacement_layer``), exported
(``export_stage``: .usda / .usdc / .usdz) and checked (``validate_stage``).

Writers of one stage folder exclude each other (``stage_lock``, waiting up to
``STAGE_LOCK_TIMEOUT_S``); ``check_writable`` tells early whether an edit could be written.
Every asset path a stage names must lie inside its folder (or package) unless the caller
passes ``allow_outside=True`` (:mod:`regnf.scene_graph.boundary`).
"""

from .edit import (
    add_instance,
    add_instance_from_registration,
    add_library_object,
    new_stage,
    parse_registration,
    provenance_from_registration,
    set_instance,
)
from .errors import StageError
from .fields import ProxyConfig, field_record, load_record_field, proxy_from_trimesh
from .layout import INSTANCES as INSTANCES_PRIM
from .layout import SCENE as SCENE_PRIM
from .layout import instance_path
from .locking import STAGE_LOCK_TIMEOUT_S, check_writable, stage_lock
from .model import ComposedScene, FieldRecord, InstanceRecord, ProxyMesh, RegistrationProvenance
from .package import export_stage
from .replacement import make_replacement_layer, original_poses, original_selections
from .summary import discovery_line, summarize
from .usd_read import read_stage, replacement_base
from .usd_write import write_stage
from .validation import validate_stage

__all__ = [
    "INSTANCES_PRIM",
    "SCENE_PRIM",
    "STAGE_LOCK_TIMEOUT_S",
    "ComposedScene",
    "FieldRecord",
    "InstanceRecord",
    "ProxyConfig",
    "ProxyMesh",
    "RegistrationProvenance",
    "StageError",
    "add_instance",
    "add_instance_from_registration",
    "add_library_object",
    "check_writable",
    "discovery_line",
    "export_stage",
    "field_record",
    "instance_path",
    "load_record_field",
    "make_replacement_layer",
    "new_stage",
    "original_poses",
    "original_selections",
    "parse_registration",
    "provenance_from_registration",
    "proxy_from_trimesh",
    "read_stage",
    "replacement_base",
    "set_instance",
    "stage_lock",
    "summarize",
    "validate_stage",
    "write_stage",
]
