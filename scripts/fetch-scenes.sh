#!/usr/bin/env bash
# Fetches the third-party scenes that the tests and the Sponza bench read, listed with their
# public sources, licences and SHA-256 in tests/scenes/manifest.tsv, and checks every hash.
#
#   scripts/fetch-scenes.sh [--verify] [DIR]
#
# DIR: where the scene folders go. Default: $ANCHORAGE_SCENES if set (a relative path is taken
# from the repository root, as the tests take it), else ../shared/scenes beside the repository.
# Files already there with the right hash are kept; the others are downloaded with curl or
# wget from https://raw.githubusercontent.com/REPOSITORY/COMMIT/PATH (a Git LFS file from
# media.githubusercontent.com) and kept only if their hash matches.
# --verify downloads nothing: it checks every file and exits 1 naming those missing or different.
set -euo pipefail

root=$(cd "$(dirname "$0")/.." && pwd)
manifest=$root/tests/scenes/manifest.tsv
verify=0
dir=
for arg in "$@"; do
    case $arg in
        --verify) verify=1 ;;
        -h | --help)
            sed -n '2,12p' "$0" | sed 's/^# \{0,1\}//'
            exit 0
            ;;
        -*)
            echo "fetch-scenes: unknown option $arg (see --help)" >&2
            exit 2
            ;;
        *)
            if [ -n "$dir" ]; then
                echo "fetch-scenes: one directory at most (see --help)" >&2
                exit 2
            fi
            dir=$arg
            ;;
    esac
done
if [ -z "$dir" ]; then
    dir=${ANCHORAGE_SCENES:-../shared/scenes}
    case $dir in /*) ;; *) dir=$root/$dir ;; esac
fi

sha256() {
    if command -v sha256sum >/dev/null; then
        sha256sum "$1" | cut -d' ' -f1
    else
        shasum -a 256 "$1" | cut -d' ' -f1
    fi
}

download() { # URL FILE
    if command -v curl >/dev/null; then
        curl -fsSL --retry 3 -o "$2" "$1"
    elif command -v wget >/dev/null; then
        wget -q -O "$2" "$1"
    else
        echo "fetch-scenes: needs curl or wget" >&2
        return 1
    fi
}

total=0 fetched=0 bad=0
while IFS=$'\t' read -r scene file hash _bytes repo commit path _licence; do
    case $scene in '' | '#'*) continue ;; esac
    total=$((total + 1))
    target=$dir/$scene/$file
    if [ -f "$target" ] && [ "$(sha256 "$target")" = "$hash" ]; then
        continue
    fi
    if [ $verify = 1 ]; then
        if [ -f "$target" ]; then echo "differs: $target"; else echo "missing: $target"; fi
        bad=$((bad + 1))
        continue
    fi
    mkdir -p "$dir/$scene"
    tmp=$target.part
    url=https://raw.githubusercontent.com/$repo/$commit/$path
    rm -f "$tmp"
    if download "$url" "$tmp" && [ "$(head -c 23 "$tmp" | tr -d '\0')" = "version https://git-lfs" ]; then
        url=https://media.githubusercontent.com/media/$repo/$commit/$path
        rm -f "$tmp"
        download "$url" "$tmp" || rm -f "$tmp"
    fi
    if [ ! -s "$tmp" ]; then
        echo "failed: $url" >&2
        rm -f "$tmp"
        bad=$((bad + 1))
        continue
    fi
    got=$(sha256 "$tmp")
    if [ "$got" != "$hash" ]; then
        echo "hash differs: $url (SHA-256 $got, the manifest says $hash)" >&2
        rm -f "$tmp"
        bad=$((bad + 1))
        continue
    fi
    mv -f "$tmp" "$target"
    echo "fetched $scene/$file"
    fetched=$((fetched + 1))
done <"$manifest"

if [ $bad -gt 0 ]; then
    if [ $verify = 1 ]; then
        echo "$bad of $total scene files in $dir are missing or differ from tests/scenes/manifest.tsv; fetch them with scripts/fetch-scenes.sh" >&2
    else
        echo "$bad of $total scene files could not be fetched into $dir" >&2
    fi
    exit 1
fi
echo "all $total scene files in $dir match tests/scenes/manifest.tsv ($fetched fetched)"
