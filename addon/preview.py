# SPDX-License-Identifier: GPL-3.0-or-later
"""The Gaussian preview: a Geometry Nodes modifier after the rig's Armature modifier, and
its materials (see :mod:`.build` for the mesh and attributes it reads).

``POINTS``: a fresh point cloud (Points node + Sample Index of the deformed positions and
``ms_*`` attributes; Mesh to Points would copy the rig's N vertex groups onto every
point), radius = mean σ × "Radius Scale". ``ELLIPSOIDS`` (for Cycles): Instance on Points
of an 80-face ico-sphere enclosing 3σ, scaled by σ per axis and rotated by Axes to
Rotation of the two deformed auxiliary vertices. The ellipsoid material's alpha is
``opacity · exp(−½ d²)`` with ``d`` the instance-space distance from the centre to the
camera ray (σ units), cut at 3σ; back faces are transparent; colour is emitted. Both
leave out the Gaussians whose opacity (after the lifespan below) is under the engine's
alpha threshold 1/255.

Lifespans: when the mesh carries ``ms_t_center`` / ``ms_lifespan`` (a bundle whose
Gaussians live around one time), both trees multiply the ``ms_opacity`` they store on the
points by ``exp(−½ ((t − ms_t_center) / ms_lifespan)²)``, ``t`` the engine time of the
Scene Time frame through the modifier's "Frame Start" / "Frame End" inputs (the bundle's
``scene.json`` range, :func:`engine.bundle.time_of_frame`), so viewport and renders see it
per frame. A lifespan of 0 gives a factor of exactly 1 (the Math node's divide returns 0
on a zero divisor). Meshes without the attributes get the tree without these nodes.

View-bound Gaussians: when the mesh carries ``ms_view_origin`` / ``ms_view_angle`` (per-frame
detail trusted only near the camera that saw it, :mod:`engine.train.shot_detail`), the trees
store on each point ``ms_view_dir``, the unit direction from its seed camera centre to its
deformed position, and ``ms_view_angle``; the material multiplies alpha by
``exp(−½ (sin(a) / ms_view_angle)²)``, ``a`` the angle between that direction and the ray to
the camera rendering it (Geometry ``Incoming``, so every view, viewport or render, gets its own
fade; an angle of 0 gives exactly 1 through the safe divide). The directions are taken in the
mesh's object space, which is world space as built (a result rotated as a whole turns its
detail's directions with it only where it is not rotated).
"""

from __future__ import annotations

import bpy

PREVIEW_MODES = ("POINTS", "ELLIPSOIDS")
GN_MODIFIER = "MotionSplatsPreview"
GN_TREE = {"POINTS": "MotionSplatsPoints", "ELLIPSOIDS": "MotionSplatsEllipsoids"}
AUX_AXES = 2  # auxiliary vertices per Gaussian in ELLIPSOIDS builds (local x and y axes)
#: Opacity under which a Gaussian is left out of the preview: the engine's per-pixel alpha
#: threshold (``engine/raster``: ``alpha = min(0.99, o exp(-sigma))``, skipped under 1/255).
ALPHA_MIN = 1.0 / 255.0


def _socket(sockets, name: str, index: int = 0):
    """The ``index``-th enabled socket called ``name`` (dynamic nodes hide unused ones)."""
    found = [s for s in sockets if s.name == name and getattr(s, "enabled", True)]
    return found[index]


def _named_attr(nodes, name: str, dtype: str):
    n = nodes.new("GeometryNodeInputNamedAttribute")
    n.data_type = dtype
    n.inputs["Name"].default_value = name
    return _socket(n.outputs, "Attribute")


class _Tree:
    """Small builder for the preview node groups."""

    def __init__(self, name: str, inputs=()):
        self.tree = tree = bpy.data.node_groups.new(name, "GeometryNodeTree")
        tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
        for sock_name, default, *low in inputs:  # (name, default[, minimum]): minimum 0, None for none
            s = tree.interface.new_socket(sock_name, in_out="INPUT", socket_type="NodeSocketFloat")
            s.default_value = default
            low = low[0] if low else 0.0
            if low is not None:
                s.min_value = low
        tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
        self.N, self.L = tree.nodes, tree.links
        self.gin, self.gout = self.N.new("NodeGroupInput"), self.N.new("NodeGroupOutput")
        self.index = self.N.new("GeometryNodeInputIndex").outputs["Index"]
        self.position = self.N.new("GeometryNodeInputPosition").outputs["Position"]

    def node(self, idname, **props):
        n = self.N.new(idname)
        for k, v in props.items():
            setattr(n, k, v)
        return n

    def link(self, a, b):
        if isinstance(a, (int, float, tuple)):
            b.default_value = a
        else:
            self.L.new(a, b)

    def math(self, op, a, b, kind="ShaderNodeMath"):
        n = self.node(kind, operation=op)
        self.link(a, n.inputs[0])
        self.link(b, n.inputs[1])
        scalar = kind == "ShaderNodeMath" or op in ("DOT_PRODUCT", "LENGTH", "DISTANCE")
        return n.outputs["Value"] if scalar else n.outputs["Vector"]

    def sample(self, geo, value, dtype, index):
        """``value`` (a field on the Gaussian mesh) read at ``index`` of the consuming context."""
        n = self.node("GeometryNodeSampleIndex", data_type=dtype, domain="POINT")
        self.link(geo, n.inputs["Geometry"])
        self.link(value, _socket(n.inputs, "Value"))
        self.link(index, n.inputs["Index"])
        return _socket(n.outputs, "Value")

    def store(self, geo, name, dtype, value):
        n = self.node("GeometryNodeStoreNamedAttribute", data_type=dtype, domain="POINT")
        self.link(geo, n.inputs["Geometry"])
        n.inputs["Name"].default_value = name
        self.link(value, _socket(n.inputs, "Value"))
        return n.outputs["Geometry"]

    def lifespan_window(self, geo):
        """Field ``exp(−½ ((t − ms_t_center) / ms_lifespan)²)`` of the Gaussian at the
        consuming index, ``t`` the engine time of the current frame.

        ``t = (frame − Frame Start) / (Frame End − Frame Start)`` is
        :func:`engine.bundle.time_of_frame` (0 for a one-frame range: the Math node's divide
        returns 0 on a zero divisor). The same safe divide makes ``(t − t_c) / 0`` zero, so a
        lifespan of 0 (always visible) gives ``exp(0)``, exactly 1.
        """
        frame = self.node("GeometryNodeInputSceneTime").outputs["Frame"]
        start, end = self.gin.outputs["Frame Start"], self.gin.outputs["Frame End"]
        t = self.math("DIVIDE", self.math("SUBTRACT", frame, start), self.math("SUBTRACT", end, start))
        tc = self.sample(geo, _named_attr(self.N, "ms_t_center", "FLOAT"), "FLOAT", self.index)
        life = self.sample(geo, _named_attr(self.N, "ms_lifespan", "FLOAT"), "FLOAT", self.index)
        z = self.math("DIVIDE", self.math("SUBTRACT", t, tc), life)
        return self.math("EXPONENT", self.math("MULTIPLY", self.math("MULTIPLY", z, z), -0.5), 0.0)

    def view_binding(self, out, geo, position):
        """Store ``ms_view_dir`` (unit, seed camera centre -> deformed ``position``) and
        ``ms_view_angle`` on the points ``out`` (module docstring)."""
        origin = self.sample(geo, _named_attr(self.N, "ms_view_origin", "FLOAT_VECTOR"), "FLOAT_VECTOR", self.index)
        ray = self.math("SUBTRACT", position, origin, kind="ShaderNodeVectorMath")
        n = self.node("ShaderNodeVectorMath", operation="NORMALIZE")
        self.link(ray, n.inputs[0])
        out = self.store(out, "ms_view_dir", "FLOAT_VECTOR", n.outputs["Vector"])
        angle = self.sample(geo, _named_attr(self.N, "ms_view_angle", "FLOAT"), "FLOAT", self.index)
        return self.store(out, "ms_view_angle", "FLOAT", angle)

    def splat_points(self, aux_per_gaussian: int, lifespans: bool = False, view: bool = False):
        """A new point cloud with one point per Gaussian at its (deformed) position,
        carrying ``ms_color``/``ms_opacity``, plus the sampled ``ms_scale`` field.

        With ``lifespans`` the stored ``ms_opacity`` is the mesh's times
        :meth:`lifespan_window` (the tree needs the "Frame Start" / "Frame End" inputs); with
        ``view`` the points also carry :meth:`view_binding`'s attributes.

        The points are made with the Points node and Sample Index instead of Mesh to
        Points: the rig's ~N vertex groups would otherwise be copied onto every point
        (or have to be removed, which costs seconds per frame with 2000 groups).
        """
        geo = self.gin.outputs["Geometry"]
        size = self.node("GeometryNodeAttributeDomainSize", component="MESH")
        self.link(geo, size.inputs["Geometry"])
        count = self.math("DIVIDE", size.outputs["Point Count"], float(1 + aux_per_gaussian))
        pts = self.node("GeometryNodePoints")
        self.link(count, pts.inputs["Count"])
        position = self.sample(geo, self.position, "FLOAT_VECTOR", self.index)
        self.link(position, pts.inputs["Position"])
        scale = self.sample(geo, _named_attr(self.N, "ms_scale", "FLOAT_VECTOR"), "FLOAT_VECTOR", self.index)
        out = pts.outputs["Points"]
        out = self.store(out, "ms_color", "FLOAT_COLOR",
                         self.sample(geo, _named_attr(self.N, "ms_color", "FLOAT_COLOR"), "FLOAT_COLOR", self.index))
        opacity = self.sample(geo, _named_attr(self.N, "ms_opacity", "FLOAT"), "FLOAT", self.index)
        if lifespans:
            opacity = self.math("MULTIPLY", opacity, self.lifespan_window(geo))
        out = self.store(out, "ms_opacity", "FLOAT", opacity)
        if view:
            out = self.view_binding(out, geo, position)
        return geo, pts, out, scale, count

    def drop_invisible(self, geo, domain: str):
        """``geo`` without the elements (``domain`` POINT or INSTANCE) whose stored
        ``ms_opacity`` is under :data:`ALPHA_MIN`: no pixel of theirs reaches the engine's
        alpha threshold, so the engine draws nothing of them either. For Cycles this is
        more than speed: each one a ray passes is a transparent bounce, and past
        ``min_transparent_bounces`` Cycles' Russian roulette turns bounces into noise."""
        op = _named_attr(self.N, "ms_opacity", "FLOAT")
        delete = self.node("GeometryNodeDeleteGeometry", domain=domain)
        self.link(geo, delete.inputs["Geometry"])
        self.link(self.math("LESS_THAN", op, ALPHA_MIN), delete.inputs["Selection"])
        return delete.outputs["Geometry"]

    def finish(self, geo, material):
        setmat = self.node("GeometryNodeSetMaterial")
        setmat.inputs["Material"].default_value = material
        self.link(geo, setmat.inputs["Geometry"])
        self.link(setmat.outputs["Geometry"], self.gout.inputs["Geometry"])
        return self.tree


#: The lifespan trees' inputs: the bundle's frame range (engine time 0 and 1).
FRAME_INPUTS = ("Frame Start", "Frame End")


def _frame_inputs(frame_range) -> tuple:
    """Tree inputs for the frame range (none without lifespans)."""
    if frame_range is None:
        return ()
    return tuple((name, float(v), None) for name, v in zip(FRAME_INPUTS, frame_range))


def _points_tree(material, frame_range=None, view: bool = False):
    t = _Tree(GN_TREE["POINTS"], inputs=(("Radius Scale", 1.0),) + _frame_inputs(frame_range))
    _, pts, out, scale, _ = t.splat_points(0, lifespans=frame_range is not None, view=view)
    mean = t.math("DOT_PRODUCT", scale, (1 / 3, 1 / 3, 1 / 3), kind="ShaderNodeVectorMath")
    t.link(t.math("MULTIPLY", mean, t.gin.outputs["Radius Scale"]), pts.inputs["Radius"])
    return t.finish(t.drop_invisible(out, "POINT"), material)


#: Ico-sphere radius in σ units: subdivision 2 (80 faces) has an inradius of ~0.94 of its
#: circumradius, so 3.3 encloses the 3σ sphere the shader cuts the Gaussian at.
ICO_RADIUS, ICO_SUBDIVISIONS, CUTOFF_SIGMA = 3.3, 2, 3.0


def _ellipsoid_tree(material, subdivisions: int = ICO_SUBDIVISIONS, frame_range=None, view: bool = False):
    t = _Tree(GN_TREE["ELLIPSOIDS"], inputs=_frame_inputs(frame_range))
    geo, _, out, scale, count = t.splat_points(AUX_AXES, lifespans=frame_range is not None, view=view)
    axes = []
    first_aux = t.math("ADD", count, t.math("MULTIPLY", t.index, float(AUX_AXES)))  # G + AUX·i
    for k in range(AUX_AXES):  # the deformed local x and y axes define the rotation
        aux = t.sample(geo, t.position, "FLOAT_VECTOR", t.math("ADD", first_aux, float(k)))
        axes.append(t.math("SUBTRACT", aux, t.position, kind="ShaderNodeVectorMath"))
    a2r = t.node("FunctionNodeAxesToRotation", primary_axis="X", secondary_axis="Y")
    t.link(axes[0], a2r.inputs["Primary Axis"])
    t.link(axes[1], a2r.inputs["Secondary Axis"])
    ico = t.node("GeometryNodeMeshIcoSphere")
    ico.inputs["Radius"].default_value = ICO_RADIUS  # instance space is in σ units
    ico.inputs["Subdivisions"].default_value = subdivisions
    iop = t.node("GeometryNodeInstanceOnPoints")
    t.link(out, iop.inputs["Points"])
    t.link(ico.outputs["Mesh"], iop.inputs["Instance"])
    t.link(a2r.outputs["Rotation"], iop.inputs["Rotation"])
    t.link(scale, iop.inputs["Scale"])
    return t.finish(t.drop_invisible(iop.outputs["Instances"], "INSTANCE"), material)


def _material(name: str, ellipsoid: bool, view: bool = False):
    mat = bpy.data.materials.new(name)
    if bpy.app.version < (5, 0, 0) and not mat.use_nodes:  # always node-based from 5.0
        mat.use_nodes = True
    if hasattr(mat, "surface_render_method"):
        mat.surface_render_method = "DITHERED"
    nt = mat.node_tree
    N, L = nt.nodes, nt.links
    N.clear()
    kind = "INSTANCER" if ellipsoid else "GEOMETRY"
    col = N.new("ShaderNodeAttribute")
    col.attribute_type, col.attribute_name = kind, "ms_color"
    op = N.new("ShaderNodeAttribute")
    op.attribute_type, op.attribute_name = kind, "ms_opacity"
    emit = N.new("ShaderNodeEmission")
    L.new(col.outputs["Color"], emit.inputs["Color"])
    emit.inputs["Strength"].default_value = 1.0
    transp = N.new("ShaderNodeBsdfTransparent")
    mix = N.new("ShaderNodeMixShader")
    out = N.new("ShaderNodeOutputMaterial")
    L.new(transp.outputs[0], mix.inputs[1])
    L.new(emit.outputs[0], mix.inputs[2])
    L.new(mix.outputs[0], out.inputs["Surface"])

    def math(op_name, a, b=None, value=None):
        n = N.new("ShaderNodeMath")
        n.operation = op_name
        for i, v in enumerate((a, b)):
            if v is None:
                continue
            if isinstance(v, (int, float)):
                n.inputs[i].default_value = v
            else:
                L.new(v, n.inputs[i])
        return n.outputs[0]

    def vdot(a, b):
        n = N.new("ShaderNodeVectorMath")
        n.operation = "DOT_PRODUCT"
        L.new(a, n.inputs[0])
        L.new(b, n.inputs[1])
        return n.outputs["Value"]

    alpha = op.outputs["Fac"]
    if ellipsoid:
        tc = N.new("ShaderNodeTexCoord")
        geom = N.new("ShaderNodeNewGeometry")
        vt = N.new("ShaderNodeVectorTransform")
        vt.vector_type, vt.convert_from, vt.convert_to = "VECTOR", "WORLD", "OBJECT"
        L.new(geom.outputs["Incoming"], vt.inputs["Vector"])
        p, v = tc.outputs["Object"], vt.outputs["Vector"]
        pp, pv, vv = vdot(p, p), vdot(p, v), vdot(v, v)
        d2 = math("SUBTRACT", pp, math("DIVIDE", math("MULTIPLY", pv, pv), math("MAXIMUM", vv, 1e-12)))
        g = math("EXPONENT", math("MULTIPLY", math("MAXIMUM", d2, 0.0), -0.5))
        alpha = math("MULTIPLY", alpha, g)
        alpha = math("MULTIPLY", alpha, math("LESS_THAN", d2, CUTOFF_SIGMA ** 2))  # 3σ cut
        alpha = math("MULTIPLY", alpha, math("SUBTRACT", 1.0, geom.outputs["Backfacing"]))
    if view:  # the view-bound Gaussians' fade with the parallax from their own camera
        inc = N.new("ShaderNodeNewGeometry").outputs["Incoming"]
        vdir = N.new("ShaderNodeAttribute")
        vdir.attribute_type, vdir.attribute_name = kind, "ms_view_dir"
        vang = N.new("ShaderNodeAttribute")
        vang.attribute_type, vang.attribute_name = kind, "ms_view_angle"
        cross = N.new("ShaderNodeVectorMath")
        cross.operation = "CROSS_PRODUCT"
        L.new(inc, cross.inputs[0])
        L.new(vdir.outputs["Vector"], cross.inputs[1])
        length = N.new("ShaderNodeVectorMath")
        length.operation = "LENGTH"
        L.new(cross.outputs["Vector"], length.inputs[0])
        s = math("DIVIDE", length.outputs["Value"], vang.outputs["Fac"])  # 0 where the angle is 0
        alpha = math("MULTIPLY", alpha, math("EXPONENT", math("MULTIPLY", math("MULTIPLY", s, s), -0.5)))
    L.new(math("MINIMUM", alpha, 0.99), mix.inputs["Fac"])
    return mat


def add_preview_modifier(mesh_obj, preview: str = "POINTS", frame_range=None):
    """(Re)create the Geometry Nodes preview modifier (after the Armature modifier).

    ``frame_range``: the bundle's ``(frame_start, frame_end)`` (``scene.json`` ``time``),
    required when the mesh has the ``ms_lifespan`` attribute (the opacity then follows the
    frame) and unused otherwise.
    """
    if preview not in PREVIEW_MODES:
        raise ValueError(f"preview must be one of {PREVIEW_MODES}, not {preview!r}")
    if "ms_lifespan" not in mesh_obj.data.attributes:
        frame_range = None
    elif frame_range is None:
        raise ValueError("a mesh with Gaussian lifespans needs the bundle's frame_range")
    old = mesh_obj.modifiers.get(GN_MODIFIER)
    if old is not None:
        mesh_obj.modifiers.remove(old)
    ell = preview == "ELLIPSOIDS"
    view = "ms_view_angle" in mesh_obj.data.attributes
    mat = _material("MotionSplatsEllipsoid" if ell else "MotionSplatsPoint", ell, view)
    tree = (_ellipsoid_tree(mat, frame_range=frame_range, view=view) if ell
            else _points_tree(mat, frame_range, view=view))
    if mat.name not in [m.name for m in mesh_obj.data.materials if m]:
        mesh_obj.data.materials.append(mat)
    mod = mesh_obj.modifiers.new(GN_MODIFIER, "NODES")
    mod.node_group = tree
    mesh_obj["ms_preview"] = preview
    return mod
