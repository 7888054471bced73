"""ament_python package setup for observer_ros."""

from glob import glob
import os

from setuptools import find_packages, setup

package_name = 'observer_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        (os.path.join('share', package_name), ['package.xml']),
        (os.path.join('share', package_name, 'config'), sorted(glob('config/*.yaml'))),
        (os.path.join('share', package_name, 'launch'), sorted(glob('launch/*.launch.py'))),
    ],
    install_requires=['setuptools'],
    # observer-eval-batch --dashboard: the Dask dashboard needs bokeh (optional)
    extras_require={'dashboard': ['bokeh>=3.1']},
    zip_safe=True,
    maintainer='observer_ros developers',
    maintainer_email='observer_ros@example.com',
    description='Luenberger, reduced-order and Kalman state estimators as ROS 2 nodes',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        # One name each, installed to lib/observer_ros (what `ros2 run` lists). The dash
        # names of the tools (observer-run, ...) are aliases that `make setup` adds to the
        # virtual environment's bin/ only.
        'console_scripts': [
            'plant_simulator = observer_ros.nodes.entry:plant_simulator',
            'observer = observer_ros.nodes.entry:observer',
            'compensator = observer_ros.nodes.entry:compensator',
            'recorder = observer_ros.nodes.entry:recorder',
            'container = observer_ros.nodes.entry:container',
            'observer_design = observer_ros.tools.design_report:main',
            'observer_eval = observer_ros.evaluation.evaluate:main',
            'observer_eval_batch = observer_ros.evaluation.batch:main',
            'observer_tune = observer_ros.tuning.tune:main',
            'observer_play = observer_ros.bag.play:main',
            'observer_run = observer_ros.tools.run_closed_loop:main',
            'observer_bag_recover = observer_ros.bag.recover:main',
        ],
    },
)
