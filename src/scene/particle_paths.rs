//! Which particle files a scene file may name. A scene file can come from someone the reader does
//! not trust (a CI pipeline rendering contributed scenes): by default it reads only regular files
//! inside its own folder, so that it cannot read the rest of the disk or block on a device.

use std::path::{Component, Path, PathBuf};

use super::{SceneError, invalid};
use crate::particle_files::ParticleFileError;

/// Which particle files a scene file may name ([`Scene::load_with`](super::Scene::load_with)).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ParticlePaths {
    /// Only regular files inside the scene file's folder: a path that is absolute, or whose `..`
    /// climb above the folder at any point (even to come back), or that a symbolic link leads
    /// out of, is refused. The default: a scene file from someone else reads nothing outside
    /// its folder.
    #[default]
    InsideSceneFolder,
    /// Any regular file, absolute or relative to the scene file's folder (the `render` tool's
    /// `--allow-outside-paths`): for scene files the reader trusts.
    Anywhere,
}

/// The particle file `written` (field `field`) resolves to against `base_dir`, once `paths`
/// allows it: `(resolved, file to read)`, the first for messages, the second with symbolic
/// links resolved.
pub(super) fn resolve(
    field: &str,
    written: &str,
    base_dir: &Path,
    paths: ParticlePaths,
) -> Result<(PathBuf, PathBuf), SceneError> {
    let joined = base_dir.join(written);
    let resolved = std::path::absolute(&joined).unwrap_or(joined);
    let outside = |place: &str| {
        invalid(
            field,
            format!("{written:?}"),
            format!(
                "a particle file must lie inside the scene file's folder ({place}); \
                 ParticlePaths::Anywhere (the render tool's --allow-outside-paths) allows any path"
            ),
        )
    };
    // Refused by its text alone, before the disk is asked anything about it.
    if paths == ParticlePaths::InsideSceneFolder && leaves_its_folder(written) {
        return Err(outside("it is absolute or climbs out with `..`"));
    }
    let io = |error: std::io::Error| SceneError::ParticleFile {
        field: field.to_string(),
        written: written.to_string(),
        resolved: resolved.clone(),
        error: Box::new(ParticleFileError::Io {
            path: resolved.clone(),
            source: error,
        }),
    };
    let file = resolved.canonicalize().map_err(io)?;
    if paths == ParticlePaths::InsideSceneFolder {
        let folder = base_dir.canonicalize().map_err(io)?;
        if !file.starts_with(&folder) {
            return Err(outside("a symbolic link leads out of it"));
        }
    }
    // A FIFO would block the read forever, a device such as /dev/zero never end it.
    if !std::fs::metadata(&file).map_err(io)?.is_file() {
        return Err(invalid(
            field,
            format!("{written:?}"),
            "a particle file must be a regular file, not a directory, device or pipe",
        ));
    }
    Ok((resolved, file))
}

/// `written` is absolute, or its `..` climb above its start.
fn leaves_its_folder(written: &str) -> bool {
    let mut depth = 0i32;
    for component in Path::new(written).components() {
        match component {
            Component::Prefix(_) | Component::RootDir => return true,
            Component::CurDir => {}
            Component::ParentDir => depth -= 1,
            Component::Normal(_) => depth += 1,
        }
        if depth < 0 {
            return true;
        }
    }
    false
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Scene;

    /// A scene whose one cloud reads `Csv(file)`.
    fn scene_reading(file: &str) -> String {
        format!(
            "(camera: (position: (0, 0, 5), look_at: (0, 0, 0), vertical_fov_degrees: 40, \
             width: 8, height: 8), lights: [], \
             clouds: [(medium: (extinction: 1, albedo: 0.5), particles: Csv({file:?}))])"
        )
    }

    /// `base/scenes/` holds the scene and `inside.csv`; `base/outside.csv` lies beside the folder.
    fn folders(name: &str) -> (PathBuf, PathBuf) {
        let base = std::env::temp_dir().join(format!("bpc_paths_{}_{name}", std::process::id()));
        let scenes = base.join("scenes");
        std::fs::create_dir_all(scenes.join("data")).unwrap();
        let csv = "x,y,z,radius,density\n0,0,0,1,1\n";
        std::fs::write(scenes.join("inside.csv"), csv).unwrap();
        std::fs::write(base.join("outside.csv"), csv).unwrap();
        (base, scenes)
    }

    fn load(scenes: &Path, file: &str, paths: ParticlePaths) -> Result<Scene, SceneError> {
        let text = scene_reading(file);
        let parsed = super::super::parse_scene_file(&text, "scene").unwrap();
        Scene::from_scene_file_with(parsed, scenes, paths)
    }

    #[test]
    fn only_files_inside_the_scene_folder_unless_anywhere() {
        let (base, scenes) = folders("inside");
        let outside = base.join("outside.csv");
        assert!(load(&scenes, "inside.csv", ParticlePaths::default()).is_ok());
        assert!(load(&scenes, "data/../inside.csv", ParticlePaths::default()).is_ok());
        for written in ["../outside.csv", outside.to_str().unwrap()] {
            let e = load(&scenes, written, ParticlePaths::default())
                .unwrap_err()
                .to_string();
            assert!(
                e.starts_with(&format!(
                    "clouds[0].particles is {written:?}; a particle file must \
                                        lie inside the scene file's folder"
                )) && e.contains("--allow-outside-paths"),
                "{e}"
            );
            assert_eq!(
                load(&scenes, written, ParticlePaths::Anywhere)
                    .unwrap()
                    .clouds[0]
                    .particles
                    .len(),
                1
            );
        }
        // The text alone refuses it: a file that does not exist gets the same answer, so the
        // refusal says nothing of what lies outside.
        let e = load(&scenes, "../missing.csv", ParticlePaths::default()).unwrap_err();
        assert!(matches!(e, SceneError::Invalid { .. }), "{e}");
    }

    #[cfg(unix)]
    #[test]
    fn links_out_of_the_folder_and_files_that_are_not_regular_are_refused() {
        let (base, scenes) = folders("links");
        let link = scenes.join("link.csv");
        let _ = std::fs::remove_file(&link);
        std::os::unix::fs::symlink(base.join("outside.csv"), &link).unwrap();
        let e = load(&scenes, "link.csv", ParticlePaths::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("a symbolic link leads out of it"), "{e}");
        assert!(load(&scenes, "link.csv", ParticlePaths::Anywhere).is_ok());
        for (written, paths) in [
            ("/dev/zero", ParticlePaths::Anywhere),
            (".", ParticlePaths::default()),
        ] {
            let e = load(&scenes, written, paths).unwrap_err().to_string();
            assert!(e.contains("must be a regular file"), "{written}: {e}");
        }
    }

    #[test]
    fn paths_that_leave_their_folder_by_their_text() {
        for inside in [
            "a.ply",
            "./a.ply",
            "data/a.csv",
            "data/../a.ply",
            "a/b/../../c.ply",
        ] {
            assert!(!leaves_its_folder(inside), "{inside}");
        }
        for outside in [
            "/etc/passwd",
            "../a.ply",
            "data/../../a.ply",
            "./../a.ply",
            "a/../..",
        ] {
            assert!(leaves_its_folder(outside), "{outside}");
        }
    }
}
