"""Dataset readers: ModelNet40 / ScanObjectNN HDF5, folder trees, and single point files.

Example::

    ds = open_dataset('/data/modelnet40_1024', split='test')
    xyz, label = ds[0]                  # (N, 3) float32, int
    all_xyz, labels = ds.load_all()     # (M, N, 3) float32, (M,) int64
    xyz = read_points('scan.pcd')       # (N, 3) float32, NaN points dropped
"""

from point_gn_ros.datasets.base import Dataset
from point_gn_ros.datasets.folder import FolderDataset
from point_gn_ros.datasets.h5 import H5Dataset
from point_gn_ros.datasets.modelnet40 import MODELNET40_CLASSES
from point_gn_ros.datasets.open import FORMATS, detect_format, open_dataset
from point_gn_ros.datasets.pcd import PcdHeader, read_pcd, read_pcd_header, write_pcd
from point_gn_ros.datasets.ply import read_ply
from point_gn_ros.datasets.points import POINT_EXTENSIONS, read_points
from point_gn_ros.datasets.scanobjectnn import SCANOBJECTNN_CLASSES, VARIANTS
from point_gn_ros.datasets.subsample import SUBSAMPLE_METHODS

__all__ = ['FORMATS', 'MODELNET40_CLASSES', 'POINT_EXTENSIONS', 'SCANOBJECTNN_CLASSES',
           'SUBSAMPLE_METHODS', 'VARIANTS', 'Dataset', 'FolderDataset', 'H5Dataset',
           'PcdHeader', 'detect_format', 'open_dataset', 'read_pcd', 'read_pcd_header',
           'read_ply', 'read_points', 'write_pcd']
