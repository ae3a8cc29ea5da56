"""terrain_perception: stereo terrain perception and footstep planning for quadrupeds (ROS 2 Jazzy).

Installed editable by scripts/setup.sh; the ROS 2 parts need the venv it builds.
"""
from glob import glob

from setuptools import find_packages, setup

package_name = 'terrain_perception'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*', 'build', 'build.*']),
    package_data={'terrain_perception': ['sim/robots/*.urdf']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml') + glob('config/*.xml')),
    ],
    install_requires=['numpy', 'scipy', 'numba', 'opencv-python-headless', 'open3d', 'pybullet',
                      'rosbags', 'PyYAML'],
    zip_safe=False,
    maintainer='terrain_perception maintainers',
    maintainer_email='maintainers@terrain-perception.invalid',
    description='On-board stereo terrain perception, mapping, occlusion fill and footstep '
                'planning for quadruped robots, with a pybullet simulator bridge.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'terrain-launch = terrain_ros.tools.launch:main',
            'terrain-topic = terrain_ros.tools.topic:main',
            'terrain-bag = terrain_ros.tools.bag:main',
            'terrain-bench = terrain_perception.bench.runner:main',
            'terrain-course = terrain_perception.terrain_cli:main',
            'terrain-demo = terrain_ros.tools.demo:main',
            'sim_bridge = sim_bridge.bridge_node:main',
            'stereo_node = stereo_node.node:main',
            'icp_mapper = icp_mapper_node.node:main',
            'terrain_fill = terrain_fill_node.node:main',
            'footstep_planner = footstep_planner_node.node:main',
            'walking_controller = walking_controller_node.node:main',
        ],
    },
)
