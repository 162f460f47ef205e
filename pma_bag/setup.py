from glob import glob

from setuptools import find_packages, setup

package_name = 'pma_bag'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PMA testbed team',
    maintainer_email='pma-testbed@example.org',
    description='rosbag2-compatible MCAP recording and playback for the PMA testbed.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'record = pma_bag.entry_points:record',
            'play = pma_bag.entry_points:play',
            'recover = pma_bag.recover:main',
            'info = pma_bag.info:main',
        ],
    },
)
