from glob import glob

from setuptools import find_packages, setup

package_name = 'pma_model'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    package_data={package_name: ['data/*.csv', 'data/*.yaml']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
    ],
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='PMA testbed team',
    maintainer_email='pma-testbed@example.org',
    description=('Hysteresis model, pressure_for_length service, replay and refit '
                 'for the PMA testbed.'),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'model_node = pma_model.entry_points:model_node',
            'refit = pma_model.offline.refit:main',
        ],
    },
)
