"""mocapd: the headless motion-capture tracking daemon."""

from calibkit import __version__ as __version__
