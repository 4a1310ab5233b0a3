"""Point cloud to mesh (Open3D): the scan step before a model can be built."""

from contactpose.scan.reconstruct import ScanOptions, ScanReport, ScanResult, load_cloud, scan_to_mesh

__all__ = ["ScanOptions", "ScanReport", "ScanResult", "load_cloud", "scan_to_mesh"]
