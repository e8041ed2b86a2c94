#!/bin/bash
# usage: sample.sh PID LOG OUT
pid=$1; logf=$2; out=$3; t0=$(date +%s)
echo "t_s rss_kb threads fds log_lines rec_files rec_kb" > $out
while kill -0 $pid 2>/dev/null; do
  rss=$(awk '/VmRSS/{print $2}' /proc/$pid/status 2>/dev/null)
  thr=$(awk '/Threads/{print $2}' /proc/$pid/status 2>/dev/null)
  fds=$(ls /proc/$pid/fd 2>/dev/null | wc -l)
  ll=$(wc -l < $logf)
  nf=$(ls $RECDIR 2>/dev/null | wc -l)
  kb=$(du -sk $RECDIR 2>/dev/null | cut -f1)
  echo "$(( $(date +%s) - t0 )) $rss $thr $fds $ll $nf $kb" >> $out
  sleep ${PERIOD:-30}
done
