from glob import glob

from setuptools import find_packages, setup

package_name = 'pma_control'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PMA testbed team',
    maintainer_email='pma-testbed@example.org',
    description='Length control of the PMA: model feedforward plus feedback.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'length_controller = pma_control.entry_points:length_controller',
        ],
    },
)
