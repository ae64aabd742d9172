"""The project's sim_bridge package: the interfaces of the authors' XPBD simulator bridge with the
same package, names, fields and type hashes, so that a real sim_bridge node is answered.

AUTHORS holds the field lines of the authors' definitions (smtobin/xpbd-tissue-sim,
ros_workspace/src/sim_bridge/msg/*.msg and srv/FactorGraphState.srv, read on their public
repository; comments left out, as they do not enter the hash). The RIHS01 hash each of them
makes must equal the one rosidl computed for the installed package."""
import json
from pathlib import Path

import pytest
from rosbags.typesys import Stores, get_typestore, get_types_from_msg

AUTHORS = {
    "sim_bridge/msg/VerticesList": "std_msgs/Header header\nuint32 size\nfloat64[] data\nint32[] invalid_indices\n",
    "sim_bridge/msg/FacesList": "std_msgs/Header header\nuint32 size\nint32[] data\nint32[] invalid_indices\n",
    "sim_bridge/msg/ElementsList": "std_msgs/Header header\nuint32 size\nint32[] data\nint32[] invalid_indices\n",
    "sim_bridge/msg/MeshState": ("std_msgs/Header header\nVerticesList vertices\nFacesList faces\n"
                                 "ElementsList elements\n"),
    "sim_bridge/msg/SparseMatrix": ("std_msgs/Header header\nuint32 rows\nuint32 cols\nint32[] row_indices\n"
                                    "int32[] col_indices\nfloat32[] values\n"),
    "sim_bridge/msg/FactorGraphState": "std_msgs/Header header\nMeshState sim_mesh\nSparseMatrix sim_stiffness_mat\n",
    "sim_bridge/msg/RemovedElement": ("std_msgs/Header header\ngeometry_msgs/Vector3 centroid\n"
                                      "geometry_msgs/Vector3 initial_centroid\nfloat32 rest_volume\n"),
    "sim_bridge/msg/RemovedElementArray": "std_msgs/Header header\nRemovedElement[] elements\n",
    "sim_bridge/srv/FactorGraphState_Request": ("bool compute_stiffness_matrix\nbool update_last_mesh\n"
                                                "sim_bridge/MeshState last_mesh\n"),
    "sim_bridge/srv/FactorGraphState_Response": ("sim_bridge/FactorGraphState fg_state\n"
                                                 "sim_bridge/MeshState updated_last_mesh\n"),
}


def _srv_names(obj):
    """rosbags files a type named pkg/srv/X under pkg/srv/msg/X: back to rosidl's name."""
    if isinstance(obj, str):
        return obj.replace("sim_bridge/srv/msg/", "sim_bridge/srv/")
    if isinstance(obj, (tuple, list)):
        return type(obj)(_srv_names(item) for item in obj)
    if isinstance(obj, dict):
        return {_srv_names(key): _srv_names(value) for key, value in obj.items()}
    return obj


@pytest.fixture(scope="module")
def authors_store():
    store = get_typestore(Stores.ROS2_JAZZY)
    for name, text in AUTHORS.items():
        store.register(_srv_names(get_types_from_msg(text, name)))
    return store


def _installed_hashes() -> dict[str, str]:
    import sim_bridge

    prefix = Path(sim_bridge.__file__).resolve().parents[4]  # <prefix>/lib/pythonX.Y/site-packages/sim_bridge
    hashes = {}
    for path in (prefix / "share" / "sim_bridge").glob("*/*.json"):
        for entry in json.loads(path.read_text())["type_hashes"]:
            hashes[entry["type_name"]] = entry["hash_string"]
    return hashes


@pytest.mark.parametrize("name", sorted(AUTHORS))
def test_type_hash_equals_the_authors_definition(authors_store, name):
    installed = _installed_hashes()
    assert name in installed, f"{name} is not installed"
    assert installed[name].startswith("RIHS01_")
    assert installed[name] == authors_store.hash_rihs01(name)


def test_fields_in_the_authors_order():
    import sim_bridge.msg
    import sim_bridge.srv

    assert list(sim_bridge.msg.VerticesList.get_fields_and_field_types().items()) == [
        ("header", "std_msgs/Header"), ("size", "uint32"), ("data", "sequence<double>"),
        ("invalid_indices", "sequence<int32>")]
    assert list(sim_bridge.msg.SparseMatrix.get_fields_and_field_types()) == [
        "header", "rows", "cols", "row_indices", "col_indices", "values"]
    assert sim_bridge.msg.SparseMatrix.get_fields_and_field_types()["values"] == "sequence<float>"
    assert list(sim_bridge.srv.FactorGraphState.Request.get_fields_and_field_types()) == [
        "compute_stiffness_matrix", "update_last_mesh", "last_mesh"]
    assert list(sim_bridge.srv.FactorGraphState.Response.get_fields_and_field_types().items()) == [
        ("fg_state", "sim_bridge/FactorGraphState"), ("updated_last_mesh", "sim_bridge/MeshState")]
