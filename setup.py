"""ament_python build of nrsfm_ros: works with colcon and with plain pip."""
from glob import glob

from setuptools import find_packages, setup

package_name = 'nrsfm_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'bench']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml') + glob('config/*.xml')
         + glob('config/*.json')),
    ],
    # the shipped HDM-Net model (mode hdmnet, reconstruct-image) and its record
    package_data={package_name: ['models/hdmnet.onnx', 'models/hdmnet.json']},
    install_requires=['setuptools', 'numpy', 'scipy', 'opencv-python-headless', 'rosbags',
                      'PyYAML', 'onnxruntime',   # onnxruntime: HDM-Net inference
                      'numba',                   # numba: the core's per-point kernels
                      'threadpoolctl'],          # BLAS at one thread in core/threads.py
    extras_require={'plot': ['matplotlib', 'pillow'],   # evaluate --plot / --render (gif)
                    'view': ['foxglove-sdk>=0.30.3'],    # nrsfm-ros view
                    'ray': ['ray==2.58.0'],               # nrsfm-ros process --ray
                    # nrsfm-ros train-hdmnet (the CPU wheel is enough; the ONNX export needs onnx)
                    'learning': ['torch', 'onnx']},
    zip_safe=False,   # the HDM-Net model is read from its file
    maintainer='nrsfm_ros maintainers',
    maintainer_email='maintainers@nrsfm-ros.invalid',
    description='Dense monocular NRSfM, scene flow and point set registration for ROS 2',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'nrsfm-ros = nrsfm_ros.cli:main',
            'tracker = nrsfm_ros.nodes.tracker:main',
            'reconstructor = nrsfm_ros.nodes.reconstructor:main',
            'registrar = nrsfm_ros.nodes.registrar:main',
            'scene_flow = nrsfm_ros.nodes.scene_flow:main',
        ],
    },
)
