"""Install with pip (`pip install -e .[ros,test]`) or build with colcon (ament_python)."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "lcpr_loop_closure"

setup(
    name=PACKAGE,
    version="0.1.0",
    description="Learned loop-closure detection (LCPR, VSeq2PC) for ROS 2 SLAM stacks",
    license="MIT",
    python_requires=">=3.10",
    packages=find_packages(
        include=["lcpr_common*", "lcpr_core*", "lcpr_offline*", "lcpr_ros*", "msg_tools*", "ros_common*",
                 "vseq2pc_ros*", "backend_ros*", "citysim*"]
    ),
    # PEP 561: the packages ship their inline type hints to users' type checkers.
    package_data={name: ["py.typed"] for name in ("lcpr_common", "lcpr_core", "lcpr_offline", "lcpr_ros", "msg_tools",
                                                  "ros_common", "vseq2pc_ros", "backend_ros", "citysim")},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.xml")),
        (f"share/{PACKAGE}/weights", glob("weights/*.pth")),
    ],
    install_requires=[
        # Pinned: an unpinned torch pulls several GB of CUDA packages onto CPU machines.
        "torch==2.13.0",
        "numpy>=1.24",
        "pillow>=10",
        "faiss-cpu>=1.8",
        "matplotlib>=3.7",
        "tqdm>=4.60",
        "pyyaml>=6",
        "rosbags>=0.10",
        "small_gicp>=1.0",  # registration for geometric verification
        "pykdtree>=1.3",  # exact nearest neighbours within a reach, the verifier's searches (NumPy in and out)
        "opencv-python-headless>=4.8",  # Bayer demosaicing and YUV -> RGB of camera-native encodings
        "simplejpeg>=1.6",  # scaled JPEG decoding (libjpeg-turbo), the CPU camera path; OpenCV decodes where absent
        "onnxruntime>=1.17",  # the exported network (model.precision onnx / int8 / auto)
        "onnx>=1.15",  # int8 quantisation (onnxruntime.quantization) reads and writes graphs with it
        "openvino>=2024.0",  # the faster int8 runtime on the Xeons measured (model.runtime auto / openvino)
    ],
    extras_require={
        # ROS 2 Jazzy (the LTS the design names) from PyPI for machines without a ROS installation:
        # pinned meta-packages (rclpy 7.1.6 with Fast DDS). A vehicle with a sourced system ROS 2
        # uses its own rclpy instead (scripts/setup.sh).
        "ros": ["ros-jazzy-rclpy[fastrtps]==7.1.6", "ros-jazzy-common-interfaces==5.3.6", "ros-jazzy-std-srvs==5.3.6"],
        # The pose-graph proof in lcpr_eval and the demo (optional: verification itself does not need it).
        "posegraph": ["gtsam>=4.2"],
        # nvJPEG decoding on a GPU (model.decode auto / nvjpeg): the torchvision built for the user's CUDA torch;
        # imported only with model.device cuda (PyPI's CPU torchvision does not import beside the CPU torch pin).
        "gpu": ["torchvision>=0.19"],
        # The registration comparison in benchmarks/tools/registration_compare.py, and the global alignment study
        # benchmarks/studies/global_registration.py (open3d-cpu: 105 MB; on Debian it also needs libusb-1.0-0).
        "compare": ["kiss-icp>=1.0", "kiss-matcher>=1.0", "open3d-cpu>=0.18"],
        # LiDAR odometry for the back end: the lcpr_kiss_icp node and benchmarks/tools/backend_ate.py.
        "odometry": ["kiss-icp>=1.0"],
        # Tests, and the linter and type checker CI runs before them (pinned: a new release may
        # add rules, and CI should not turn red on a clone nobody changed).
        "test": [
            "pytest>=7",
            "hypothesis>=6",
            "pytest-randomly>=3.15",
            "pytest-reverse>=1.7",
            "ruff==0.17.6",
            "mypy==2.4.1",
            "types-PyYAML",
            "types-tqdm",
            "import-linter==2.17",  # lint-imports: the layering contracts in setup.cfg
        ],
        # The documentation site (mkdocs.yml, docs/): `mkdocs build --strict`, which CI runs, and `mkdocs serve`.
        # Pinned for the same reason as the test tools: a new release may add warnings, and --strict fails on them.
        "docs": ["mkdocs==1.6.1", "mkdocs-material==9.8.2"],
    },
    zip_safe=True,
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "lcpr_demo = lcpr_ros.demo:main",
            "lcpr_keyframe_demo = lcpr_offline.lcpr_keyframe_demo:main",
            "lcpr_quantize = lcpr_offline.lcpr_quantize:main",
            "lcpr_node = lcpr_ros.node:main",
            "lcpr_backend = backend_ros.node:main",
            "lcpr_kiss_icp = backend_ros.kiss_icp_node:main",
            "lcpr_replay = lcpr_ros.replay:main",
            "lcpr_eval = lcpr_ros.evaluate:main",
            "lcpr_relocalize = lcpr_offline.relocalize:main",
            "lcpr_fleet = lcpr_offline.fleet:main",
            "vseq2pc_node = vseq2pc_ros.node:main",
            "lcpr_train = lcpr_offline.lcpr_train:main",
            "vseq2pc_cache = lcpr_offline.vseq2pc_cache:main",
            "vseq2pc_train = lcpr_offline.vseq2pc_train:main",
            "vseq2pc_eval = lcpr_offline.vseq2pc_evaluate:main",
            "msg_tools_nuscenes2bag = msg_tools.convert.nuscenes:main",
            "msg_tools_kitti2bag = msg_tools.convert.kitti:main",
            "msg_tools_scans2bag = msg_tools.convert.scans2bag:main",
            "msg_tools_baginfo = msg_tools.convert.baginfo:main",
            "citysim = citysim.cli:main",
            "msg_tools_synth = citysim.cli:main",  # the same command under the name interfaces.md gives it
        ],
    },
)
