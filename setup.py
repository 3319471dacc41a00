"""ament_python package set-up: `colcon build` and `pip install -e .` both use it."""

from glob import glob

from setuptools import find_packages, setup

package_name = 'point_gn_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    package_data={package_name: ['data/*.npz', 'data/*.json', 'core/kernels/*.c', 'core/kernels/*.h']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
        ('share/' + package_name + '/banks', glob('point_gn_ros/data/*default*.npz')),
    ],
    install_requires=['setuptools', 'numpy', 'h5py', 'scipy', 'tqdm'],
    zip_safe=False,
    maintainer='point_gn_ros maintainers',
    maintainer_email='point-gn-ros@example.com',
    description='Online Point-GN classification of segmented PointCloud2 objects.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'classifier_node = point_gn_ros.node.classifier_node:main',
            'point_gn = point_gn_ros.cli:main',
        ],
    },
)
