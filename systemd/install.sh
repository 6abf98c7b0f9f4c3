#!/usr/bin/env bash
# Install vgripd as a systemd service (systemd/README.md): a virtual environment with the
# package, the documentation pages the unit names, the unit with its paths, a first config if
# there is none (`vgripd init`), then `vgripd check` and `systemd-analyze verify`.
#
#   sudo systemd/install.sh                                  # from this checkout
#   sudo systemd/install.sh --package 'vgripd-0.1.0-py3-none-any.whl[pylon]' --example pylon-stereo
#
# Every path can be moved (the tests install into a temporary folder this way):
#   --prefix DIR      the venv and the docs (default /opt/vgripd)
#   --etc DIR         the config folder, the unit's working directory (default /etc/vgripd)
#   --state DIR       the writable cell includes of `vgripd init` (default /var/lib/vgripd)
#   --unit-dir DIR    where the unit goes (default /etc/systemd/system)
#   --package SPEC    what pip installs (default: this checkout; a wheel, 'vgripd[s7]', ...)
#   --pip-option OPT  passed to pip install (repeatable: --no-deps, --no-index, ...)
#   --example NAME    the first config from config/examples/NAME.toml (default: the demo cell)
#   --allow-edit      the first config lets the web view save (`vgripd init --allow-edit`)
#   --no-systemctl    do not run `systemctl daemon-reload` (a prefix outside the system's)
# Environment: PYTHON, the interpreter of the venv (default python3, >= 3.11).
set -euo pipefail

here="$(cd "$(dirname "$0")" && pwd)"
prefix=/opt/vgripd
etc=/etc/vgripd
state=/var/lib/vgripd
unit_dir=/etc/systemd/system
package="$(dirname "$here")"
pip_options=()
init_options=()
systemctl=yes

while (($#)); do
    case "$1" in
        --prefix) prefix="$2"; shift 2 ;;
        --etc) etc="$2"; shift 2 ;;
        --state) state="$2"; shift 2 ;;
        --unit-dir) unit_dir="$2"; shift 2 ;;
        --package) package="$2"; shift 2 ;;
        --pip-option) pip_options+=("$2"); shift 2 ;;
        --example) init_options+=(--example "$2"); shift 2 ;;
        --allow-edit) init_options+=(--allow-edit); shift ;;
        --no-systemctl) systemctl=no; shift ;;
        -h|--help) sed -n '2,21p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
        *) echo "install.sh: unknown option $1 (--help lists them)" >&2; exit 2 ;;
    esac
done

for dir in "$prefix" "$etc" "$state" "$unit_dir"; do
    [[ $dir == /?* ]] || { echo "install.sh: paths must be absolute, not '$dir'" >&2; exit 2; }
done
venv="$prefix/venv"
vgripd="$venv/bin/vgripd"

echo "== venv $venv"
"${PYTHON:-python3}" -m venv "$venv"
"$venv/bin/python" -m pip install -q ${pip_options[@]+"${pip_options[@]}"} "$package"

# The files that travel with the package (vgripd/share/): the unit's template and the pages
# its Documentation= names, read from the installed package, not from a checkout.
share="$("$venv/bin/python" -c 'from vgripd.resources import shared; print(shared())')"

echo "== docs $prefix/docs"
rm -rf "$prefix/docs"
cp -rL "$share/docs" "$prefix/docs"   # -L: real files also from an editable install

echo "== unit $unit_dir/vgripd.service"
install -d "$unit_dir"
sed -e "s|/opt/vgripd/venv/bin/vgripd|$vgripd|g" \
    -e "s|file:///opt/vgripd/docs/|file://$prefix/docs/|g" \
    -e "s|/etc/vgripd/vgripd.toml|$etc/vgripd.toml|g" \
    -e "s|^WorkingDirectory=/etc/vgripd\$|WorkingDirectory=$etc|" \
    "$share/systemd/vgripd.service" > "$unit_dir/vgripd.service.new"
chmod 0644 "$unit_dir/vgripd.service.new"
mv "$unit_dir/vgripd.service.new" "$unit_dir/vgripd.service"

echo "== config $etc/vgripd.toml"
if [[ -e "$etc/vgripd.toml" ]]; then
    echo "kept (it exists)"
else
    "$vgripd" init -c "$etc/vgripd.toml" --state-dir "$state" ${init_options[@]+"${init_options[@]}"}
fi
# The cameras are the service's to open: judge the config without them here.
"$vgripd" check --no-camera -c "$etc/vgripd.toml"

echo "== systemd-analyze verify"
systemd-analyze verify "$unit_dir/vgripd.service"

if [[ $systemctl == yes ]]; then
    systemctl daemon-reload
fi
echo "installed; start it with: systemctl enable --now vgripd"
