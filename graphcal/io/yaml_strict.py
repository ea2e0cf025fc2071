"""The one YAML loader of graphcal: safe (plain Python types only, nothing is unpickled), refuses
duplicate keys (naming the first line), and reads YAML 1.2 floats such as ``1e-3`` as numbers
(PyYAML's YAML 1.1 rules read them as text). Used for dataset.yaml and calibration.yaml.

It refuses aliases (``*name``, and so merge keys ``<<: *name``): an input file has no need of them,
and a few lines of nested aliases expand into billions of nodes (a "billion laughs" bomb)."""

from __future__ import annotations

import re

import yaml

__all__ = ["StrictSafeLoader"]


class StrictSafeLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses duplicate keys and reads YAML 1.2 floats such as ``1e-3``
    (PyYAML's YAML 1.1 rules read them as text). Constructs only plain Python types."""

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(
                None, None, f"found an alias (*{event.anchor}): graphcal reads YAML without aliases "
                "(write the value out where it is used)", event.start_mark,
            )  # fmt: skip
        return super().compose_node(parent, index)

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen: dict[tuple, int] = {}
            for key_node, _ in node.value:
                if isinstance(key_node, yaml.ScalarNode) and key_node.tag != "tag:yaml.org,2002:merge":
                    k = (key_node.tag, key_node.value)
                    if k in seen:
                        raise yaml.constructor.ConstructorError(
                            "while constructing a mapping", node.start_mark,
                            f"found duplicate key {key_node.value!r} (first on line {seen[k] + 1})",
                            key_node.start_mark,
                        )  # fmt: skip
                    seen[k] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


StrictSafeLoader.yaml_implicit_resolvers = {k: list(v) for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()}
StrictSafeLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)
