"""ament_python build description for gnsscam_ros."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'gnsscam_ros'
#: Source folders never installed (test/test_wheel_contents.py checks the wheel).
EXCLUDED_PACKAGES = ['test', 'test.*', 'tools', 'tools.*']

setup(
    name=PACKAGE,
    version='0.1.0',
    # tools/ (the fault-injection kit, fixture cutters) is the workshop, not the product.
    packages=find_packages(exclude=EXCLUDED_PACKAGES),
    # The node processes' Fast DDS profile (gnsscam_ros/nodes/memory.py).
    package_data={'gnsscam_ros.nodes': ['fastdds_profile.xml']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='gnsscam_ros maintainers',
    maintainer_email='maintainers@gnsscam-ros.invalid',
    description='GNSS-camera particle filter with integrity risk for ROS 2 Jazzy',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'gnsscam_eval = gnsscam_ros.evaluation.cli:main',
            'gnsscam_bench = gnsscam_ros.bench.filter:main',
            'gnsscam_mapdb = gnsscam_ros.vision.mapdb_cli:main',
            'gnsscam_convert = gnsscam_ros.bags.convert_cli:main',
            'gnsscam_replay = gnsscam_ros.live.replay:main',
            'gnsscam_record = gnsscam_ros.live.record:main',
            'gnss_node = gnsscam_ros.nodes.gnss_node:main',
            'camera_node = gnsscam_ros.nodes.camera_node:main',
            'imu_node = gnsscam_ros.nodes.imu_node:main',
            'fusion_node = gnsscam_ros.nodes.fusion_node:main',
            'pipeline_node = gnsscam_ros.nodes.pipeline:main',
        ],
    },
)
