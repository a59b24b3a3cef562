"""The editing panel of ``regnf view``: moving an instance and refining its pose, drawing a box
and registering a new instance in it, each written to the stage only on "accept" or "add
instance" (:mod:`regnf.viewer.stage_viewer`, whose viewer this is a part of)."""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from regnf.scene_graph import ComposedScene, add_instance_from_registration, read_stage
from regnf.viewer import messages
from regnf.viewer.editing import (
    DEFAULT_BOX_SIZE,
    MIN_BOX_SIZE,
    EditState,
    gone,
    refine_from_pose,
    register_box,
    write_refined,
)
from regnf.viewer.render_worker import client_pose, wxyz_of


def instance_table(scene: ComposedScene) -> str:
    """Markdown table of the stage's instances: id, class, library object, confidence, source."""
    rows = ["| instance | class | object | confidence | found by |", "|---|---|---|---|---|"]
    for iid, inst in scene.instances.items():
        label = scene.library[inst.library_name].label if inst.library_name in scene.library else "?"
        reg = inst.registration
        if reg is None:
            conf, how = "-", "placed by hand"
        else:
            conf = f"{reg.confidence:.3f}"
            how = "discovery" if reg.discovery is not None else reg.method
            if not reg.accepted:
                how += ", forced" if reg.forced else ", rejected"
        rows.append(f"| {iid} | {label} | {inst.library_name} | {conf} | {how} |")
    if not scene.instances:
        rows.append("| (no instances) | | | | |")
    return "\n".join(rows)


class EditPanel:
    """The editing controls and their actions, a part of :class:`~regnf.viewer.stage_viewer.StageViewer`
    (its server, stage, watcher and status fields)."""

    def _add_editing(self) -> None:
        gui = self.server.gui
        # Folded until opened: a page builds folded controls later, and opens faster
        # (docs/decisions/rendering-speed.md).
        with gui.add_folder("Edit", expand_by_default=False):
            self.move_button = gui.add_button("move selected")
            self.refine_button = gui.add_button("refine", disabled=True)
            self.accept_button = gui.add_button("accept", disabled=True)
            self.reject_button = gui.add_button("reject", disabled=True)
            self.edit_status = gui.add_markdown("")
        with gui.add_folder("New instance", expand_by_default=False):
            names = sorted(self.scene.library) or ["(empty library)"]
            self.new_object = gui.add_dropdown("library object", names, initial_value=names[0])
            self.new_size = gui.add_vector3("box size (m)", initial_value=DEFAULT_BOX_SIZE,
                                            min=(MIN_BOX_SIZE,) * 3, step=0.05)
            self.draw_button = gui.add_button("draw box")
            self.register_button = gui.add_button("register box", disabled=True)
            self.add_button = gui.add_button("add instance", disabled=True)
            self.new_status = gui.add_markdown("")
        self.new_box: dict[str, Any] = {}
        for handle, action, what, status in (
                (self.draw_button, lambda: self.draw_box(), "draw box", self.new_status),
                (self.register_button, lambda: self.register_box_async(), "register box", self.new_status),
                (self.add_button, lambda: self.add_new_instance(), "add instance", self.new_status),
                (self.move_button, lambda: self.start_edit(self.selected.value), "move selected", self.edit_status),
                (self.refine_button, lambda: self.refine_async(), "refine", self.edit_status),
                (self.accept_button, lambda: self.accept(), "accept", self.edit_status),
                (self.reject_button, lambda: self.reject(), "reject", self.edit_status)):
            handle.on_click(self._quiet(lambda _, act=action: act(), what, status))
        self.new_size.on_update(self._quiet(lambda _: self._size_box(), "box size", self.new_status))

    def _stage_ready(self, status: Any, action: str, write: bool = False) -> bool:
        """Whether ``action`` may go on. The stage is reloaded first if another program changed
        it; the action is refused (``status`` says why) while the stage on disk cannot be read
        and, for a write, when it has just changed (the user sees the new stage first)."""
        changed = self.watch.sync()
        if self.watch.error is not None:
            status.content = f"{action} refused: the stage on disk cannot be read now ({self.watch.error})"
            return False
        if changed and write:
            status.content = (f"{self.stage.name} was changed on disk by another program and is reloaded: "
                              f"check it, then press {action} again")
            return False
        return True

    def start_edit(self, iid: str) -> None:
        """Put a transform gizmo, with the library proxy, on instance ``iid``."""
        if not self._stage_ready(self.edit_status, "move selected"):
            return
        inst = self.scene.instances.get(iid)
        if inst is None or inst.library_name not in self.scene.library:
            messages.ignored("an unknown instance", iid)
            self.edit_status.content = f"no instance **{iid}** in the stage: choose one in the list"
            return
        self.reject()
        M = inst.object_to_scene
        s = float(np.cbrt(np.linalg.det(M[:3, :3])))
        gizmo = self.server.scene.add_transform_controls(
            "/edit/gizmo", scale=max(0.3, s), position=tuple(M[:3, 3]),
            wxyz=wxyz_of(M[:3, :3] / s))
        rec = self.scene.library[inst.library_name]
        self.server.scene.add_mesh_simple("/edit/gizmo/proxy", rec.proxy.points * s, rec.proxy.faces,
                                          color=(255, 90, 60), opacity=0.6)
        self.edit = EditState(iid, s, gizmo)
        self.refine_button.disabled = False
        self.reject_button.disabled = False
        self.accept_button.disabled = True
        self.edit_status.content = f"drag **{iid}** near its place, then press refine"

    def gizmo_pose(self) -> np.ndarray | None:
        """(4, 4) object -> scene metres of the gizmo, at the edited instance's scale (None,
        logged, when what the client sent is not a pose)."""
        assert self.edit is not None
        g = self.edit.gizmo
        placed = messages.pose(g.position, g.wxyz, "the gizmo")
        return None if placed is None else client_pose(*placed) @ np.diag([self.edit.scale] * 3 + [1.0])

    def refine_async(self) -> threading.Thread | None:
        """Start :meth:`refine` on its own thread (never in a GUI callback's)."""
        if self.edit is None or not self._stage_ready(self.edit_status, "refine"):
            return None
        edit = self.edit
        if edit is None:
            return None  # its instance left the stage: the reload said so
        start = self.gizmo_pose()
        if start is None:
            self.edit_status.content = f"the pose of **{edit.instance_id}**'s gizmo is not a pose: move it again"
            return None
        self.refine_button.disabled = True
        self.edit_status.content = f"refining **{edit.instance_id}** ..."
        thread = threading.Thread(target=self._refine_job, args=(edit, start), daemon=True)
        thread.start()
        return thread

    def _refine_job(self, edit: EditState, start: np.ndarray) -> None:
        try:
            with self._job_lock:
                payload = refine_from_pose(self.stage, self.scene, self.composites, edit.instance_id, start)
        except Exception as exc:  # noqa: BLE001 (reported in the panel; the viewer keeps running)
            self.edit_status.content = f"refine failed: {type(exc).__name__}: {exc}"
            self.refine_button.disabled = False
            return
        with self._edit_lock:
            if self.edit is not edit:
                return  # rejected (or another edit started) meanwhile
            edit.payload = payload
            O = np.asarray(payload["object_to_scene_metres"])
            s = float(np.cbrt(np.linalg.det(O[:3, :3])))
            edit.gizmo.position = tuple(O[:3, 3])
            edit.gizmo.wxyz = wxyz_of(O[:3, :3] / s)
        verdict = "accepted" if payload["accepted"] else "below the acceptance threshold"
        self.edit_status.content = (f"refined **{edit.instance_id}**: confidence {payload['confidence']:.3f} "
                                    f"({verdict}); accept writes it to the stage")
        self.refine_button.disabled = False
        self.accept_button.disabled = False

    def accept(self) -> None:
        """Write the refined pose of the edited instance to the stage."""
        edit = self.edit
        if edit is None or edit.payload is None:
            return
        with self.watch.lock:  # no reload between the check and the write
            ready = self._stage_ready(self.edit_status, "accept", write=True)
            if self.edit is not edit:
                self.edit_status.content = gone(edit.instance_id)
                return
            if not ready:
                return
            try:
                with self.watch.writing():
                    write_refined(self.stage, edit.instance_id, edit.payload, self.config.allow_outside)
            except Exception as exc:  # noqa: BLE001 (reported in the panel; the stage is unchanged)
                self.edit_status.content = f"accept failed: {' '.join(str(exc).split())}"
                return
        self._end_edit(edit, f"**{edit.instance_id}** written to {self.stage.name}")

    def _end_edit(self, edit: EditState, message: str) -> None:
        """Remove the gizmo of ``edit`` (if still the current one) and say ``message``."""
        with self._edit_lock:
            if self.edit is not edit:
                return
            self.edit = None
        self.server.scene.remove_by_name("/edit/gizmo")
        for button in (self.refine_button, self.accept_button, self.reject_button):
            button.disabled = True
        self.edit_status.content = message

    def draw_box(self) -> None:
        """A proposal box standing on the floor below the scene's centre, with a gizmo."""
        if not self._stage_ready(self.new_status, "draw box"):
            return
        lo, hi = self.scene.scene.proxy.extent.astype(np.float64)
        half = 0.5 * self._box_size()
        centre = np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), max(lo[2], 0.0) + half[2]])
        gizmo = self.server.scene.add_transform_controls("/new/gizmo", scale=float(max(half.max(), 0.3)),
                                                          position=tuple(centre))
        self.new_box = {"gizmo": gizmo, "payload": None}
        self._size_box()
        self.register_button.disabled = False
        self.add_button.disabled = True
        self.new_status.content = "drag the box around an object, choose the object, press register box"

    def _box_size(self) -> np.ndarray:
        """(3,) size in metres of the panel's box, within [MIN_BOX_SIZE, the room's largest side];
        a size that is not finite (logged) is put back to the default."""
        lo, hi = self.scene.scene.proxy.extent.astype(np.float64)
        size = messages.box_size(self.new_size.value, MIN_BOX_SIZE, max(float((hi - lo).max()), MIN_BOX_SIZE))
        size = np.asarray(DEFAULT_BOX_SIZE) if size is None else size
        if tuple(size) != tuple(self.new_size.value):
            self.new_size.value = tuple(float(v) for v in size)  # its own update redraws the box
        return size

    def _size_box(self) -> None:
        if self.new_box:
            self.server.scene.add_box("/new/gizmo/box", color=(60, 200, 255),
                                      dimensions=tuple(float(v) for v in self._box_size()), wireframe=True)

    def new_box_pose(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(4, 4) rigid pose in scene metres and (3,) half extents of the drawn box (None, logged,
        when what the client sent is not a pose)."""
        g = self.new_box["gizmo"]
        placed = messages.pose(g.position, g.wxyz, "the box")
        return None if placed is None else (client_pose(*placed), 0.5 * self._box_size())

    def register_box_async(self) -> threading.Thread | None:
        """Start the registration inside the drawn box on its own thread."""
        if not self.new_box or not self._stage_ready(self.new_status, "register box"):
            return None
        placed = self.new_box_pose()
        name = messages.known(self.new_object.value, self.scene.library, "library object")
        if placed is None or name is None:
            self.new_status.content = ("the box's pose is not a pose: move it again" if placed is None else
                                       f"no library object **{self.new_object.value}** in the stage: choose one")
            return None
        pose, half = placed
        self.register_button.disabled = True
        self.new_status.content = f"registering **{name}** ..."
        box = self.new_box

        def job() -> None:
            try:
                with self._job_lock:
                    payload = register_box(self.scene, self.composites, name, pose, half)
            except Exception as exc:  # noqa: BLE001 (reported in the panel)
                self.new_status.content = f"registration failed: {type(exc).__name__}: {exc}"
                self.register_button.disabled = False
                return
            if self.new_box is not box:
                return
            box["payload"] = payload
            verdict = "accepted" if payload["accepted"] else "below the acceptance threshold"
            self.new_status.content = (f"**{name}**: confidence {payload['confidence']:.3f} ({verdict}); "
                                       "add instance writes it to the stage")
            self.register_button.disabled = False
            self.add_button.disabled = False

        thread = threading.Thread(target=job, daemon=True)
        thread.start()
        return thread

    def add_new_instance(self) -> str | None:
        """Write the registration of the drawn box as a new instance; returns its id."""
        payload = self.new_box.get("payload") if self.new_box else None
        if payload is None:
            return None
        with self.watch.lock:  # no reload between the check and the write
            if not self._stage_ready(self.new_status, "add instance", write=True):
                return None
            try:
                with self.watch.writing():
                    iid = add_instance_from_registration(self.stage, payload, force=not payload["accepted"],
                                                         allow_outside=self.config.allow_outside)
            except Exception as exc:  # noqa: BLE001 (reported in the panel; the stage is unchanged)
                self.new_status.content = f"add instance failed: {' '.join(str(exc).split())}"
                return None
        self.server.scene.remove_by_name("/new/gizmo")
        self.new_box = {}
        self.register_button.disabled = True
        self.add_button.disabled = True
        self.new_status.content = f"**{iid}** added to {self.stage.name}"
        return iid

    def _reload_from_disk(self, other: bool) -> None:
        """:meth:`_reload` for the stage's watcher (``other``: another program changed it)."""
        try:
            self._reload()
        except (ValueError, OSError) as exc:
            self.stage_status.content = (f"{self.stage.name} changed on disk and cannot be read now; shown as it "
                                         f"was, edits wait: {' '.join(str(exc).split())}")
            raise
        self.stage_status.content = (f"{self.stage.name} was changed on disk by another program: reloaded"
                                     if other else "")

    def _reload(self) -> None:
        """Re-read the stage after an edit or a change on disk: proxies, table, lists,
        composites, renders; an edit whose instance left the stage is dropped."""
        self.scene = read_stage(self.stage, allow_outside=self.config.allow_outside)
        self.composites.reset(self.scene)
        for mesh in self._meshes:
            mesh.remove()
        self._meshes = []
        self._show_proxies()
        self.table.content = instance_table(self.scene)
        ids = list(self.scene.instances) or ["(none)"]
        self.selected.options = ids
        self.new_object.options = sorted(self.scene.library) or ["(empty library)"]
        self._select()
        edit = self.edit
        if edit is not None and edit.instance_id not in self.scene.instances:
            self._end_edit(edit, gone(edit.instance_id))
        self._request_all()

    def reject(self) -> None:
        """Drop the edit: the stage is left untouched."""
        edit = self.edit
        if edit is not None:
            self._end_edit(edit, "edit dropped; the stage is unchanged")
