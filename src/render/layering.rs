//! `render/` reads one way: core → extract → plan → illumination → view → draw, and no file's
//! imports lead back to it. This test parses every `crate::render::…` path in `src/render/`
//! (`cargo test --lib layering` shows a violation with its file and path).

use std::{
    collections::{BTreeMap, BTreeSet},
    path::{Path, PathBuf},
};

/// The folders in the order imports may run, lowest first.
const FOLDERS: [&str; 6] = ["core", "extract", "plan", "illumination", "view", "draw"];

/// A module of `render/` as its path below it: `["plan", "pools"]`; a folder's `mod.rs` is the
/// folder's own path, `render/mod.rs` and the test modules beside it the empty path's files.
type Module = Vec<String>;

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

fn module_of(root: &Path, file: &Path) -> Module {
    let relative = file.strip_prefix(root).unwrap().with_extension("");
    let mut parts: Module = relative
        .components()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect();
    if parts.last().is_some_and(|p| p == "mod") {
        parts.pop();
    }
    parts
}

/// Every path a file reaches through `crate::render::` (a braced group gives one per item),
/// comments left out.
fn render_paths(source: &str) -> Vec<Vec<String>> {
    let code: String = source
        .lines()
        .map(|l| l.split("//").next().unwrap())
        .collect::<Vec<_>>()
        .join("\n");
    let mut paths = Vec::new();
    for (at, _) in code.match_indices("crate::render::") {
        let rest = &code[at + "crate::render::".len()..];
        let items: Vec<&str> = match rest.strip_prefix('{') {
            Some(group) => top_level_items(group),
            None => vec![rest],
        };
        for item in items {
            let path: Vec<String> = item
                .split("::")
                .map(|s| {
                    s.trim()
                        .chars()
                        .take_while(|c| c.is_alphanumeric() || *c == '_')
                })
                .map(String::from_iter)
                .take_while(|s| !s.is_empty())
                .collect();
            if !path.is_empty() {
                paths.push(path);
            }
        }
    }
    paths
}

/// The comma-separated items of a braced group (`group` starts after its `{`).
fn top_level_items(group: &str) -> Vec<&str> {
    let (mut depth, mut start, mut items) = (0, 0, Vec::new());
    for (i, c) in group.char_indices() {
        match c {
            '{' => depth += 1,
            '}' if depth == 0 => {
                items.push(&group[start..i]);
                break;
            }
            '}' => depth -= 1,
            ',' if depth == 0 => {
                items.push(&group[start..i]);
                start = i + 1;
            }
            _ => {}
        }
    }
    items
}

fn rank(module: &Module) -> usize {
    module
        .first()
        .and_then(|f| FOLDERS.iter().position(|x| x == f))
        .unwrap_or(FOLDERS.len())
}

/// The modules of `render/` and the modules each one imports.
fn import_graph() -> BTreeMap<Module, BTreeSet<Module>> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("src/render");
    let mut files = Vec::new();
    rust_files(&root, &mut files);
    let modules: BTreeSet<Module> = files.iter().map(|f| module_of(&root, f)).collect();
    let mut graph = BTreeMap::new();
    for file in &files {
        let module = module_of(&root, file);
        let mut imports = BTreeSet::new();
        for path in render_paths(&std::fs::read_to_string(file).unwrap()) {
            // The longest prefix of the path that is a module: the file it reaches.
            let target = (1..=path.len())
                .rev()
                .map(|n| path[..n].to_vec())
                .find(|p| modules.contains(p))
                .unwrap_or_else(|| {
                    panic!("{}: `{}` names no folder", file.display(), path.join("::"))
                });
            if target != module {
                imports.insert(target);
            }
        }
        graph
            .entry(module)
            .or_insert_with(BTreeSet::new)
            .extend(imports);
    }
    graph
}

/// A cycle through `start`, if one exists (depth-first).
fn cycle_from(graph: &BTreeMap<Module, BTreeSet<Module>>, start: &Module) -> Option<Vec<Module>> {
    fn walk(
        graph: &BTreeMap<Module, BTreeSet<Module>>,
        start: &Module,
        path: &mut Vec<Module>,
        seen: &mut BTreeSet<Module>,
    ) -> bool {
        let here = path.last().unwrap().clone();
        for next in graph.get(&here).into_iter().flatten() {
            if next == start {
                return true;
            }
            if seen.insert(next.clone()) {
                path.push(next.clone());
                if walk(graph, start, path, seen) {
                    return true;
                }
                path.pop();
            }
        }
        false
    }
    let mut path = vec![start.clone()];
    walk(graph, start, &mut path, &mut BTreeSet::new()).then_some(path)
}

#[test]
fn imports_run_one_way_between_the_folders() {
    let graph = import_graph();
    assert!(graph.len() >= 40, "found {} modules", graph.len());
    for (module, imports) in &graph {
        if module.is_empty() || rank(module) == FOLDERS.len() {
            continue; // render/mod.rs and its tests wire everything together
        }
        for target in imports {
            assert!(
                !target.is_empty() && rank(target) <= rank(module),
                "render/{} imports render/{}, which comes after it",
                module.join("/"),
                target.join("/"),
            );
        }
    }
}

#[test]
fn no_file_of_render_imports_itself_through_others() {
    let graph = import_graph();
    for module in graph.keys() {
        if let Some(cycle) = cycle_from(&graph, module) {
            let names: Vec<String> = cycle.iter().map(|m| m.join("/")).collect();
            panic!("an import circle: {} → back", names.join(" → "));
        }
    }
}

#[test]
fn the_parser_finds_grouped_and_single_paths() {
    let source = "use crate::render::{core::gpu::{A, B}, plan::pools::C};\n\
                  // crate::render::draw::commented\n\
                  let x = crate::render::view::sort::f();";
    let paths = render_paths(source);
    let first: Vec<&str> = paths.iter().map(|p| p[0].as_str()).collect();
    assert_eq!(first, ["core", "plan", "view"]);
    assert_eq!(paths[0], ["core", "gpu"]);
}
