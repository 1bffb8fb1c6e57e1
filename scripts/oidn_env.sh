# Sourced by scripts/setup.sh, test.sh and fuzz.sh: exports OIDN_DIR, the Open Image Denoise
# library that the venv's pyoidn wheel ships, which the `denoise` feature links (see build.rs).
# Needs .venv (scripts/setup.sh makes it).
OIDN_DIR=$(.venv/bin/python -c 'import importlib.util as u, os; print(os.path.join(u.find_spec("pyoidn").submodule_search_locations[0], "oidn"))')
export OIDN_DIR
