"""Digitises the reward curve the article's notebook plots (`plt.plot(history)`, cell 32 of
TF2_SpaceInvaders_GC.ipynb) from its saved PNG: for each pixel column, the episodes it covers and
the vertical extent of the line in reward units, and one pixel row in reward units (see
docs/experiment/notebook/README.md).

usage: python3 tools/notebook/digitize_plot.py PLOT.png [COVERAGE_THRESHOLD] > plot-digitized.csv
"""
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from png_decode import read_png
w,h,R=read_png(sys.argv[1])
def cov(p):
    r,g,b,a=p
    if a==0: return 0.0
    # line color (31,119,180) over white; use red channel
    if not (b>r+20): return 0.0
    return max(0.0,min(1.0,(255-r)/(255-31)))
# calibration by least squares on tick pixel centres
def fit(pix,val):
    n=len(pix); mx=sum(val)/n; my=sum(pix)/n
    s=sum((v-mx)*(p-my) for v,p in zip(val,pix))/sum((v-mx)**2 for v in val)
    return s, my-s*mx
# The tick marks' pixel positions, read off the PNG: x ticks 0, 100, ..., 800 and y ticks
# 0, 200, ..., 800.
xt=[48,86,124,162,200,239,277,315,353]; sx,ox=fit([t+0.5 for t in xt],[0,100,200,300,400,500,600,700,800])
yt=[216,171,127,82,37]; sy,oy=fit([t+0.5 for t in yt],[0,200,400,600,800])
print('x: px = %.5f*ep + %.3f ; y: px = %.5f*r + %.3f'%(sx,ox,sy,oy),file=sys.stderr)
ep=lambda X:(X-ox)/sx; rw=lambda Y:(Y-oy)/sy
# frame-based autoscale check
print('xlim from frame', ep(33.5), ep(368.5), ' ylim', rw(224.5), rw(6.5),file=sys.stderr)
rows=[]
TH=float(sys.argv[2]) if len(sys.argv)>2 else 0.5
for x in range(34,368):
    ys=[y for y in range(7,224) if cov(R[y][x])>=TH]
    if not ys: continue
    top=min(ys)+0.5+0.75; bot=max(ys)+0.5-0.75
    if bot<top: top=bot=(top+bot)/2
    lo=ep(x); hi=ep(x+1)
    e0=max(0,math.ceil(lo)); e1=math.ceil(hi)-1
    rows.append((x,lo,hi,e0,e1,rw(bot),rw(top)))
# One pixel row in reward units: every episode lies within a column's extent to about this.
px=abs(1/sy)
print('pixel_col,episode_x_from,episode_x_to,first_episode_index,last_episode_index,reward_min,reward_max,reward_per_pixel')
for r in rows: print('%d,%.2f,%.2f,%d,%d,%.1f,%.1f,%.2f'%(r+(px,)))
