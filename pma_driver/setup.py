from glob import glob

from setuptools import find_packages, setup

package_name = 'pma_driver'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/firmware/pma_firmware', glob('firmware/pma_firmware/*')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PMA testbed team',
    maintainer_email='pma-testbed@example.org',
    description='Serial driver and firmware for the PMA testbed.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'driver_node = pma_driver.entry_points:driver_node',
        ],
    },
)
