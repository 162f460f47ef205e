from setuptools import find_packages, setup

package_name = 'pma_cli'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PMA testbed team',
    maintainer_email='pma-testbed@example.org',
    description='The `pma` command line: status, setpoints, sweeps, calibration, CSV export.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'pma = pma_cli.entry_points:pma',
        ],
    },
)
