from glob import glob

from setuptools import find_packages, setup

package_name = 'cgags_ros'

setup(
    name=package_name,
    version='0.1.0',
    # Only the package and its subpackages (each needs an __init__.py); test/ and bench/
    # are not installed.
    packages=find_packages(include=[package_name, package_name + '.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml') + glob('config/*.xml')),
        ('share/' + package_name + '/launch', glob('launch/*.py')),
        ('share/' + package_name + '/rviz', glob('rviz/*.rviz')),
    ],
    install_requires=['setuptools', 'numpy', 'scipy', 'PyYAML'],
    zip_safe=True,
    maintainer='cgags_ros maintainers',
    maintainer_email='maintainers@cgags-ros.invalid',
    description='Global point cloud registration (compatibility graph + accelerated guided '
                'sampling) for ROS 2',
    license='MIT',
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'register_node = cgags_ros.register_node:main',
            'cgags-register = cgags_ros.tools.register_cli:main',
            'cgags-replay = cgags_ros.tools.replay:main',
            'cgags-demo = cgags_ros.tools.demo:main',
            'cgags-calibrate = cgags_ros.tools.calibrate_cli:main',
            'cgags-relocalize = cgags_ros.tools.relocalize_cli:main',
            'cgags-tune = cgags_ros.tools.tune:main',
            'cgags-map = cgags_ros.tools.map_cli:main',
        ],
    },
)
