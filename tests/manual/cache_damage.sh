#!/usr/bin/env bash
# The compile cache under each damage: exit code, stderr lines, and the CSV against a run without
# cache. A manual check, run with the project installed (`coopjax` on PATH); the full-disk case needs
# root (a 64 kB tmpfs). tests/test_cache.py is the automatic one.
set -u
W=/tmp/dmg; rm -rf $W; mkdir -p $W; cd $W
unset JAX_COMPILATION_CACHE_DIR
run() { COOPJAX_CACHE=$1 coopjax simulate --scenario paper --out r.csv > /dev/null 2> err; echo "$? $(grep -c . err) $(cmp -s r.csv ref.csv && echo same || echo DIFF) $(head -c 150 err | tr '\n' '|')"; }
COOPJAX_CACHE= coopjax simulate --scenario paper --out ref.csv > /dev/null 2>&1
run $W/c > /dev/null  # fill
sub=$(ls -d $W/c/*/); entries=($(ls $sub*-cache))
fresh() { rm -rf $W/d; cp -a $W/c $W/d; sub=$(ls -d $W/d/*/); entries=($(ls $sub*-cache)); }
fresh; cp ${entries[0]} /tmp/x; cp ${entries[1]} ${entries[0]}; cp /tmp/x ${entries[1]}; echo "swapped:    $(run $W/d)"
fresh; truncate -s 100 ${entries[0]}; echo "truncated:  $(run $W/d)"
fresh; : > ${entries[0]}; echo "emptied:    $(run $W/d)"
fresh; python -c "import sys;p=sys.argv[1];b=bytearray(open(p,'rb').read());b[len(b)//2]^=0xFF;open(p,'wb').write(b)" ${entries[0]}; echo "bit-flipped: $(run $W/d)"
fresh; head -c 5000 /dev/urandom > ${entries[0]}; echo "random:     $(run $W/d)"
fresh; rm $sub/coopjax-sums.json; echo "no sums:    $(run $W/d)"
fresh; echo "copied:     $(run $W/d)"
mkdir -p $W/full; mount -t tmpfs -o size=64k tmpfs $W/full && { echo "full disk:  $(run $W/full/c)"; umount $W/full; }
