//! Integration tests, one binary (STYLE.md §10). Third-party scenes are read from
//! `../shared/scenes/`; the Python checks (OpenEXR, usd-core, usd2gltf) use the virtual
//! environment that `.ci/run` creates in `.venv`.

mod it;
