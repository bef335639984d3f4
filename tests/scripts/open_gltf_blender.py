"""Opens psscan's material.gltf in Blender, as an artist would (File > Import > glTF 2.0), and
prints one JSON line saying what Blender built: the mesh's size, the material's Principled BSDF
inputs and the images wired into them, and anything the importer reported.

usage: blender --background --factory-startup --python open_gltf_blender.py -- MATERIAL.gltf

Exit status 0 when the import ran (the caller judges the JSON), 1 when it raised.
"""
import json
import sys

import bpy
import numpy

# Debian 12's Blender 3.4 importer still writes `np.bool`, an alias of the builtin `bool` that
# Debian's NumPy 1.24 removed; put the alias back so the importer runs as it does with the
# NumPy Blender ships (nothing of psscan's is involved).
if not hasattr(numpy, "bool"):
    numpy.bool = bool


def linked_image(socket):
    """The image feeding `socket`, through at most a Normal Map or Separate node."""
    todo = [link.from_node for link in socket.links]
    while todo:
        node = todo.pop()
        if node.type == "TEX_IMAGE" and node.image is not None:
            return node.image
        for inp in node.inputs:
            todo.extend(link.from_node for link in inp.links)
    return None


def describe_image(image):
    if image is None:
        return None
    return {
        "name": image.name,
        "size": list(image.size),
        "colorspace": image.colorspace_settings.name,
        # has_data is False until pixels are read; reading them proves the file decoded.
        "pixels": len(image.pixels),
    }


def main(path):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    result = bpy.ops.import_scene.gltf(filepath=path)
    meshes = [o for o in bpy.context.scene.objects if o.type == "MESH"]
    out = {"import": sorted(result), "meshes": len(meshes)}
    if meshes:
        obj = meshes[0]
        out["dimensions_m"] = [round(v, 6) for v in obj.dimensions]
        out["faces"] = len(obj.data.polygons)
        materials = [slot.material for slot in obj.material_slots if slot.material]
        out["materials"] = len(materials)
        if materials:
            mat = materials[0]
            bsdf = next(n for n in mat.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
            inputs = {}
            for name in ("Base Color", "Normal", "Roughness", "Metallic", "Sheen", "Sheen Tint"):
                if name not in bsdf.inputs:
                    continue
                socket = bsdf.inputs[name]
                entry = {"linked": socket.is_linked}
                if socket.is_linked:
                    entry["image"] = describe_image(linked_image(socket))
                elif hasattr(socket, "default_value"):
                    value = socket.default_value
                    entry["value"] = list(value) if hasattr(value, "__len__") else value
                inputs[name] = entry
            out["material"] = {"name": mat.name, "inputs": inputs}
    print("BLENDER_JSON " + json.dumps(out))


if __name__ == "__main__":
    args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    try:
        main(args[0])
    except Exception as e:  # noqa: BLE001 - reported to the caller as the failure
        print("BLENDER_JSON " + json.dumps({"error": f"{type(e).__name__}: {e}"}))
        sys.exit(1)
