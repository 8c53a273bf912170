"""The one exception type lightplane raises for bad input.

Every public function that rejects its input raises :class:`LightplaneError`
with a message that names the argument, file or placement at fault.  The
command line turns it into one line on stderr and exit status 2.
"""

from __future__ import annotations


class LightplaneError(ValueError):
    """Bad input or an impossible request; the message says which and why."""
