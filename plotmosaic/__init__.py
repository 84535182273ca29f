"""plotmosaic: targetless, GNSS-free co-registration of forest LiDAR scans."""

__version__ = "0.1.0"
