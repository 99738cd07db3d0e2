#!/usr/bin/env python3
"""Import circles between a crate's modules.

usage: module_cycles.py SRC_DIR [DEPTH]   (exit 1 when there is a circle)

Every `crate::a::b`, `crate::{a, b}` and `super::…` path outside `#[cfg(test)]` is resolved to
the module it names (the longest module path it starts with); a module is cut to DEPTH
components (2: `http::stream_ws`, `session::track`). Paths between a module and its own
ancestors or descendants are left out: a parent declares its children. A circle is a strongly
connected component of more than one module (Tarjan's algorithm).
"""
import os
import re
import sys


def modules_of(root):
    files = []
    for folder, _, names in os.walk(root):
        for name in names:
            if name.endswith('.rs'):
                path = os.path.join(folder, name)
                parts = os.path.relpath(path, root)[:-3].split(os.sep)
                if parts[-1] in ('mod', 'lib', 'main'):
                    parts = parts[:-1]
                files.append((path, tuple(parts)))
    return files


def edges_of(root, depth):
    files = modules_of(root)
    known = {module for _, module in files}

    def resolve(parts):
        for k in range(len(parts), 0, -1):
            if tuple(parts[:k]) in known:
                return tuple(parts[:k])
        return None

    edges = {}
    for path, module in files:
        if not module:
            continue
        with open(path, encoding='utf-8') as f:
            source = f.read()
        source = re.sub(r'//[^\n]*', '', source).split('#[cfg(test)]')[0]
        targets = [t.split('::') for t in re.findall(r'\bcrate::(\w+(?:::\w+)*)', source)]
        for group in re.findall(r'\bcrate::\{([^}]*)\}', source):
            targets += [[n.strip().split('::')[0]] for n in group.split(',') if n.strip()]
        for supers, rest in re.findall(r'\b((?:super::)+)(\w+(?:::\w+)*)', source):
            base = list(module[:len(module) - supers.count('super::')])
            targets.append(base + rest.split('::'))
        me = module[:depth]
        for target in targets:
            found = resolve(target)
            if found is None:
                continue
            other = found[:depth]
            if other == me[:len(other)] or me == other[:len(me)]:
                continue
            edges.setdefault(me, set()).add(other)
    return edges


def circles(edges):
    index, low, stack, on_stack, found = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    nodes = set(edges).union(*edges.values()) if edges else set()
    sys.setrecursionlimit(10000)
    for v in sorted(nodes):
        if v not in index:
            visit(v)
    return found


def main():
    root = sys.argv[1]
    depth = int(sys.argv[2]) if len(sys.argv) > 2 else 2
    edges = edges_of(root, depth)
    found = circles(edges)
    count = sum(len(v) for v in edges.values())
    print(f'{root}: {len(edges)} modules importing, {count} imports, depth {depth}')
    for component in found:
        print('circle: ' + ' <-> '.join('::'.join(m) for m in component))
    sys.exit(1 if found else 0)


if __name__ == '__main__':
    main()
