"""Building the address space of :mod:`.address_space` into an asyncua server.

Imported only in the server process (:mod:`.worker`), so the service never loads asyncua.
Every length, wavelength and duration is an ``AnalogItemType`` variable with its
``EngineeringUnits`` (UNECE Rec. 20 code, OPC 10000-8 section 5.6.3) and ``EURange``; every
node carries a Description, and ``ReloadModel``'s arguments are named and described.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable

from asyncua import ua
from asyncua.common.node_factory import make_node

from fbgcomp.runtime.health import FLAG_NAMES, STATUS_NAMES
from fbgcomp.runtime.outputs.opcua.address_space import (
    AXES,
    DESCRIPTIONS,
    UNECE_NAMESPACE_URI,
    UNITS,
    eu_range,
    unece_unit_id,
)


def eu_information(unit: str):
    """``ua.EUInformation`` of one of :data:`UNITS` (``"um"``, ``"nm"``, ``"ms"``)."""
    code, display, description = UNITS[unit]
    return ua.EUInformation(
        NamespaceUri=UNECE_NAMESPACE_URI,
        UnitId=unece_unit_id(code),
        DisplayName=ua.LocalizedText(display),
        Description=ua.LocalizedText(description),
    )


def reload_model_arguments():
    """``ReloadModel``'s input and output arguments (``ua.Argument``), named and described."""

    def arg(name):
        return ua.Argument(
            Name=name,
            DataType=ua.NodeId(ua.ObjectIds.String),
            ValueRank=ua.ValueRank.Scalar,
            ArrayDimensions=[],
            Description=ua.LocalizedText(DESCRIPTIONS[f"ReloadModel.{name}"]),
        )

    return [arg("ModelFile")], [arg("Result")]


async def add_variable(parent, nodeid, qname, variant, description, unit=None, eu_range=None, prop=False):
    """A read-only scalar variable with its Description; with ``unit`` (a key of
    :data:`UNITS`) an ``AnalogItemType`` with ``EngineeringUnits`` and ``EURange``.

    asyncua's ``add_variable`` always types a variable ``BaseDataVariableType``, so the
    node is added with the same AddNodes service call it makes, naming the type.
    """
    item = ua.AddNodesItem()
    item.RequestedNewNodeId = nodeid
    item.BrowseName = qname
    item.NodeClass = ua.NodeClass.Variable
    item.ParentNodeId = parent.nodeid
    if prop:
        item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasProperty)
        item.TypeDefinition = ua.NodeId(ua.ObjectIds.PropertyType)
    else:
        item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasComponent)
        item.TypeDefinition = ua.NodeId(
            ua.ObjectIds.AnalogItemType if unit else ua.ObjectIds.BaseDataVariableType
        )
    attrs = ua.VariableAttributes()
    attrs.DisplayName = ua.LocalizedText(qname.Name)
    attrs.Description = description
    attrs.DataType = ua.NodeId(getattr(ua.ObjectIds, variant.VariantType.name))
    attrs.Value = variant
    attrs.ValueRank = ua.ValueRank.Scalar
    attrs.ArrayDimensions = None
    attrs.WriteMask = attrs.UserWriteMask = 0
    attrs.Historizing = False
    attrs.AccessLevel = attrs.UserAccessLevel = ua.AccessLevel.CurrentRead.mask
    item.NodeAttributes = attrs
    result = (await parent.session.add_nodes([item]))[0]
    result.StatusCode.check()
    node = make_node(parent.session, result.AddedNodeId)
    if unit:
        base = nodeid.Identifier
        await node.add_property(
            ua.NodeId(f"{base}.EngineeringUnits", nodeid.NamespaceIndex),
            ua.QualifiedName("EngineeringUnits", 0),
            eu_information(unit),
            datatype=ua.ObjectIds.EUInformation,
        )
        low, high = eu_range
        await node.add_property(
            ua.NodeId(f"{base}.EURange", nodeid.NamespaceIndex),
            ua.QualifiedName("EURange", 0),
            ua.Range(Low=float(low), High=float(high)),
            datatype=ua.ObjectIds.Range,
        )
    return node


async def build_address_space(
    server,
    idx: int,
    sensor_names: list[str],
    model_id: str,
    enabled: bool,
    eu_ranges: dict,
    reload_model: Callable,
) -> dict:
    """Add the ``FbgComp`` object, its type, variables and ``ReloadModel`` method to ``server``.

    ``idx`` is the index of :data:`~.address_space.NAMESPACE`, ``eu_ranges`` the EURange
    overrides (:func:`~.address_space.eu_range`), ``reload_model`` the method's callback.
    Returns the variable nodes by path (``"CorrectionX_um"``, ``"Sensors.S1.Status"``...).
    """

    def nid(name):
        return ua.NodeId(ua.String(f"FbgComp.{name}"), ua.Int16(idx))

    def text(key, **fields):
        return ua.LocalizedText(DESCRIPTIONS[key].format(**fields))

    def rng(kind, sensor=None):
        return eu_range(eu_ranges, kind, sensor)

    # our own ObjectType, so a client can recognise the compensator; it stands for
    # OPC 40501-1's ElementMonitoringType (docs/opcua-cnc.md)
    ctype = await server.nodes.base_object_type.add_object_type(
        ua.NodeId(ua.String("ThermalCompensationType"), ua.Int16(idx)),
        ua.QualifiedName("ThermalCompensationType", idx),
    )
    await ctype.write_attribute(
        ua.AttributeIds.Description, ua.DataValue(ua.Variant(text("ThermalCompensationType")))
    )
    root = await server.nodes.objects.add_object(
        ua.NodeId(ua.String("FbgComp"), ua.Int16(idx)),
        ua.QualifiedName("FbgComp", idx),
        objecttype=ctype.nodeid,
    )
    await root.write_attribute(ua.AttributeIds.Description, ua.DataValue(ua.Variant(text("FbgComp"))))
    await add_variable(
        root,
        nid("Name"),
        ua.QualifiedName("Name", idx),
        ua.Variant("fbgcomp thermal compensation", ua.VariantType.String),
        text("Name"),
        prop=True,
    )
    nodes = {}

    async def var(parent, path, name, value, vtype, description, unit=None, eu_range=None):
        node = await add_variable(
            parent,
            nid(path),
            ua.QualifiedName(name, idx),
            ua.Variant(value, vtype),
            description,
            unit=unit,
            eu_range=eu_range,
        )
        nodes[path] = node
        return node

    D, S, B, T = (
        ua.VariantType.Double,
        ua.VariantType.String,
        ua.VariantType.Boolean,
        ua.VariantType.DateTime,
    )
    for prefix in ("Correction", "PredictedDeviation", "IntervalHalfWidth", "ExpectedError"):
        for a in AXES:
            await var(
                root, f"{prefix}{a}_um", f"{prefix}{a}_um", 0.0, D, text(prefix, a=a), "um", rng(prefix, a)
            )
    # the offset + Z slope form a CNC's thermal compensation takes (docs/cnc-integration.md)
    for a in AXES:
        await var(root, f"Offset{a}_um", f"Offset{a}_um", 0.0, D, text("Offset", a=a), "um", rng("Offset"))
        await var(
            root,
            f"Slope{a}_um_per_m",
            f"Slope{a}_um_per_m",
            0.0,
            D,
            text("Slope", a=a),
            "um_per_m",
            rng("Slope"),
        )
    await var(root, "ZRef_mm", "ZRef_mm", 0.0, D, text("ZRef_mm"), "mm", rng("ZRef_mm"))
    await var(root, "SampleTime", "SampleTime", dt.datetime.now(dt.UTC), T, text("SampleTime"))
    await var(root, "Latency_ms", "Latency_ms", 0.0, D, text("Latency_ms"), "ms", rng("Latency_ms"))
    await var(root, "ModelId", "ModelId", model_id, S, text("ModelId"))
    await var(root, "Health", "Health", "STARTING", S, text("Health"))
    await var(root, "Alarm", "Alarm", False, B, text("Alarm"))
    await var(root, "FallbackInUse", "FallbackInUse", "", S, text("FallbackInUse"))
    flags = ", ".join(f"{bit} {name}" for bit, name in FLAG_NAMES.items())
    for a in AXES:
        await var(
            root,
            f"OutputFlags{a}",
            f"OutputFlags{a}",
            0,
            ua.VariantType.Byte,
            text("OutputFlags", a=a, flags=flags),
        )
    await var(root, "Limited", "Limited", False, B, text("Limited"))
    await var(root, "OutputFlags", "OutputFlags", "", S, text("OutputFlagsText"))
    await var(root, "SourceStatus", "SourceStatus", "", S, text("SourceStatus"))
    await var(root, "FramesProcessed", "FramesProcessed", 0, ua.VariantType.UInt64, text("FramesProcessed"))
    await var(root, "Heartbeat", "Heartbeat", 0, ua.VariantType.UInt32, text("Heartbeat"))
    enabled_node = await var(root, "Enabled", "Enabled", bool(enabled), B, text("Enabled"))
    await enabled_node.set_writable(True)
    sensors = await root.add_folder(nid("Sensors"), ua.QualifiedName("Sensors", idx))
    await sensors.write_attribute(ua.AttributeIds.Description, ua.DataValue(ua.Variant(text("Sensors"))))
    statuses = ", ".join(STATUS_NAMES)
    for s in sensor_names:
        obj = await sensors.add_object(nid(f"Sensors.{s}"), ua.QualifiedName(s, idx))
        await obj.write_attribute(ua.AttributeIds.Description, ua.DataValue(ua.Variant(text("Sensor", s=s))))
        await var(
            obj, f"Sensors.{s}.Status", "Status", "UNKNOWN", S, text("Sensors.Status", statuses=statuses)
        )
        await var(
            obj,
            f"Sensors.{s}.Wavelength_nm",
            "Wavelength_nm",
            float("nan"),
            D,
            text("Sensors.Wavelength_nm"),
            "nm",
            rng("Wavelength_nm", s),
        )
    inputs, outputs = reload_model_arguments()
    method = await root.add_method(
        nid("ReloadModel"), ua.QualifiedName("ReloadModel", idx), reload_model, inputs, outputs
    )
    await method.write_attribute(ua.AttributeIds.Description, ua.DataValue(ua.Variant(text("ReloadModel"))))
    return nodes
