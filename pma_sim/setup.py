from glob import glob

from setuptools import find_packages, setup

package_name = 'pma_sim'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/simavr', glob('simavr/*')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PMA testbed team',
    maintainer_email='pma-testbed@example.org',
    description='The simulated rig of the PMA testbed: muscle families, fake_arduino, '
                'simavr_arduino.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'fake_arduino = pma_sim.entry_points:fake_arduino',
            'simavr_arduino = pma_sim.entry_points:simavr_arduino',
        ],
    },
)
