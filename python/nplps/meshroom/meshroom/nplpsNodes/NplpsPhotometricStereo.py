"""Meshroom node: near-light photometric stereo with nplps, one reconstruction per pose of an SfMData."""

from meshroom.core import desc

__version__ = "1.0"


class NplpsPhotometricStereo(desc.CommandLineNode):
    """Near-light photometric stereo (nplps) on each pose of an SfMData.

    The views of the SfMData that share a poseId are the images of one pose, each under one
    light; the lights come from a lights file (AliceVision lights.json, RelightLab .lp or .dome,
    or an nplps rig file), the camera from the SfMData's intrinsics. For each pose the node writes
    <poseId>_normals.png (16-bit RGB, OpenGL or OpenCV frame) and a folder <poseId>/ with the
    mesh (mesh.ply, mesh.obj), albedo.png, depth.tiff and the other files of an nplps result.
    """

    commandLine = (
        "nplps meshroom {inputPathValue} --output {outputValue} --lights {lightsValue} "
        "--depth {depthValue} --normal-frame {normalFrameValue} --camera-distance {cameraDistanceValue} "
        "--mask-folder {maskFolderValue} --overwrite"
    )
    category = "Photometric Stereo"
    documentation = __doc__

    inputs = [  # noqa: RUF012 (Meshroom's node description is a class attribute)
        desc.File(
            name="inputPath",
            label="SfMData",
            description="Input SfMData file: the views sharing a poseId are the images of one pose.",
            value="",
        ),
        desc.File(
            name="lights",
            label="Lights File",
            description="lights.json, .lp, .dome or nplps rig file (empty: lights.json beside the SfMData).",
            value="",
        ),
        desc.File(
            name="maskFolder",
            label="Mask Folder",
            description="Folder of <poseId>.png masks (empty: every pixel).",
            value="",
        ),
        desc.StringParam(
            name="depth",
            label="Working Distance",
            description="Distance from the camera to the object, in the lights' unit, or 'auto'.",
            value="auto",
        ),
        desc.FloatParam(
            name="cameraDistance",
            label="Camera Distance (.dome/.lp)",
            description="Distance from the camera to the .dome frame's origin on the object plane (0: not needed).",
            value=0.0,
            range=(0.0, 100000.0, 1.0),
        ),
        desc.ChoiceParam(
            name="normalFrame",
            label="Normal Frame",
            description="Frame of the normal maps: OpenGL (y up, z towards the viewer) or OpenCV (y down, z forward).",
            value="opengl",
            values=["opengl", "opencv"],
            exclusive=True,
        ),
    ]

    outputs = [  # noqa: RUF012
        desc.File(
            name="output",
            label="Output Folder",
            description="One folder per pose with the mesh, albedo, depth and the normals.",
            value="{nodeCacheFolder}",
        ),
        desc.File(
            name="normals",
            label="Normal Maps",
            description="The 16-bit normal map of each pose.",
            semantic="image",
            value="{nodeCacheFolder}/<POSE_ID>_normals.png",
            group="",
        ),
        desc.File(
            name="meshes",
            label="Meshes",
            description="The mesh of each pose.",
            value="{nodeCacheFolder}/<POSE_ID>/mesh.obj",
            group="",
        ),
    ]
