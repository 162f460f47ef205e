"""Message definitions in rosbag2's `ros2msg` schema layout, from the sourced environment.

rosbag2 (jazzy, LocalMessageDefinitionSource) stores the root `.msg` verbatim, then each
dependency once, depth first in sorted order, behind a line of 80 `=` and `MSG: pkg/Type`.
Readers such as Foxglove, rosbags and mcap_ros2 decode from that text alone, so it must come
from the installed interface files (share/<pkg>/msg/*.msg), never from a copy in our code.
"""

from __future__ import annotations

import json
import os
import re
import sys
from dataclasses import dataclass
from functools import cache
from pathlib import Path

from pma_bag.errors import SchemaError

SCHEMA_DELIMITER = '=' * 80
PRIMITIVE_TYPES = frozenset({
    'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16',
    'int32', 'uint32', 'int64', 'uint64', 'string', 'wstring',
})
# First token of a field line: optional `pkg/`, the type, optional bound or array suffix.
_FIELD_TYPE = re.compile(r'^\s*(?:([A-Za-z0-9_]+)/)?([A-Za-z0-9_]+)(?:<=\d+)?(?:\[[^\]]*\])?\s+\S')
_TYPE_NAME = re.compile(r'^([A-Za-z0-9_]+)/(?:msg/)?([A-Za-z0-9_]+)$')
TYPE_HASH_PATTERN = re.compile(r'^RIHS01_[0-9a-f]{64}$')


@dataclass(frozen=True)
class MessageSchema:
    """What a bag stores about a type: `pkg/msg/Type`, schema encoding and text, RIHS01 hash."""

    type_name: str
    encoding: str
    text: str
    type_hash: str  # '' when the environment has no type description for it


def split_type_name(type_name: str) -> tuple[str, str]:
    """'pkg/msg/Type' or 'pkg/Type' -> ('pkg', 'Type')."""
    match = _TYPE_NAME.match(type_name)
    if not match:
        raise SchemaError(f'{type_name!r} is not a message type name like pkg/msg/Type')
    return match.group(1), match.group(2)


def share_directories() -> list[Path]:
    """Install prefixes' share/ directories, AMENT_PREFIX_PATH first, then this Python's."""
    prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    seen: list[Path] = []
    for prefix in prefixes:
        share = Path(prefix) / 'share'
        if share not in seen and share.is_dir():
            seen.append(share)
    return seen


def interface_file(package: str, name: str, suffix: str) -> Path | None:
    """The first share/<package>/msg/<name><suffix> on the search path, or None."""
    for share in share_directories():
        path = share / package / 'msg' / f'{name}{suffix}'
        if path.is_file():
            return path
    return None


def msg_dependencies(text: str, package: str) -> list[str]:
    """Complex field types of a .msg text as sorted 'pkg/Type' names (rosbag2's std::set)."""
    found = set()
    for raw_line in text.splitlines():
        line = raw_line.split('#', 1)[0]
        match = _FIELD_TYPE.match(line)
        if not match:
            continue
        dep_package, dep_type = match.group(1), match.group(2)
        if dep_package is None and dep_type in PRIMITIVE_TYPES:
            continue
        found.add(f'{dep_package or package}/{dep_type}')
    return sorted(found)


def _msg_text(package: str, name: str) -> str:
    path = interface_file(package, name, '.msg')
    if path is None:
        searched = ', '.join(str(s) for s in share_directories()) or 'nothing'
        raise SchemaError(
            f'no definition of {package}/msg/{name}: share/{package}/msg/{name}.msg not found '
            f'(searched {searched}; is the package built and sourced?)')
    return path.read_text(encoding='utf-8')


@cache
def message_definition(type_name: str) -> str:
    """Full `ros2msg` schema text of a type, dependencies appended the way rosbag2 does."""
    package, name = split_type_name(type_name)
    seen: set[str] = set()

    def append_recursive(dep_package: str, dep_name: str) -> str:
        text = _msg_text(dep_package, dep_name)
        for dependency in msg_dependencies(text, dep_package):
            if dependency in seen:
                continue
            seen.add(dependency)
            sub_package, sub_name = dependency.split('/')
            text += f'\n{SCHEMA_DELIMITER}\nMSG: {dependency}\n'
            text += append_recursive(sub_package, sub_name)
        return text

    return append_recursive(package, name)


@cache
def type_hash(type_name: str) -> str:
    """RIHS01 hash of a type from its installed type description, '' if there is none."""
    package, name = split_type_name(type_name)
    path = interface_file(package, name, '.json')
    if path is None:
        return ''
    try:
        description = json.loads(path.read_text(encoding='utf-8'))
    except (OSError, ValueError):
        return ''
    full_name = f'{package}/msg/{name}'
    for entry in description.get('type_hashes', []):
        if entry.get('type_name') == full_name:
            return str(entry.get('hash_string', ''))
    return ''


def message_schema(type_name: str) -> MessageSchema:
    """Schema record contents for a type; raises SchemaError if its .msg is not installed."""
    package, name = split_type_name(type_name)
    full_name = f'{package}/msg/{name}'
    return MessageSchema(full_name, 'ros2msg', message_definition(full_name), type_hash(full_name))
