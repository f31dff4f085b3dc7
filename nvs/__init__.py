"""nvs: novel view synthesis via depth-guided skip connections (Hou, Solin, Kannala, WACV 2021)."""

__version__ = "0.1.0"
