from glob import glob

from setuptools import find_packages, setup

package_name = 'pma_bringup'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
        ('share/' + package_name + '/foxglove', glob('foxglove/*.json')),
        ('share/' + package_name + '/plotjuggler', glob('plotjuggler/*.xml')),
        ('share/' + package_name + '/config', glob('config/*.xml')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PMA testbed team',
    maintainer_email='pma-testbed@example.org',
    description='Launch files, the end-to-end demo and the live view (Foxglove) of the '
                'PMA testbed.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'demo = pma_bringup.demo:main',
            'foxglove_live = pma_bringup.entry_points:foxglove_live',
        ],
    },
)
