"""
The bond nav2_lifecycle_manager watches, formed with bondpy when it is importable.

Jazzy's ``ros-jazzy-bondpy`` always provides it, and ``package.xml`` declares it; the
fallback (no bond, and a warning naming the manager's ``bond_timeout: 0.0``) remains for
stacks without a bondpy wheel, such as this package's emulated Jazzy test stack.
"""

from __future__ import annotations

from typing import Any


def start_bond(node: Any) -> Any:
    """Form the bond nav2_lifecycle_manager watches, when bondpy is importable (else None)."""
    try:
        from bondpy.bondpy import Bond
    except ImportError:
        return None
    try:
        bond = Bond(node, 'bond', node.get_name())
        bond.start()
    except Exception as exc:  # noqa: BLE001 - bondpy's API differs between releases
        node.get_logger().warning(f'bondpy is importable but the bond failed: {exc!r}; set '
                                  "the lifecycle manager's bond_timeout: 0.0")
        return None
    return bond
