"""A minimal PNG reader (8-bit RGBA, no interlace) in plain Python, for digitize_plot.py."""
import zlib, struct
def read_png(fn):
    b=open(fn,'rb').read(); assert b[:8]==b'\x89PNG\r\n\x1a\n'
    p=8; idat=b''
    while p<len(b):
        n,=struct.unpack('>I',b[p:p+4]); t=b[p+4:p+8]; d=b[p+8:p+8+n]; p+=12+n
        if t==b'IHDR': w,h,bd,ct,_,_,il=struct.unpack('>IIBBBBB',d)
        elif t==b'IDAT': idat+=d
    assert bd==8 and ct==6 and il==0
    raw=zlib.decompress(idat); bpp=4; stride=w*bpp; rows=[]; prev=bytearray(stride); i=0
    for y in range(h):
        f=raw[i]; line=bytearray(raw[i+1:i+1+stride]); i+=1+stride
        for x in range(stride):
            a=line[x-bpp] if x>=bpp else 0; up=prev[x]; c=prev[x-bpp] if x>=bpp else 0
            if f==1: line[x]=(line[x]+a)&255
            elif f==2: line[x]=(line[x]+up)&255
            elif f==3: line[x]=(line[x]+((a+up)>>1))&255
            elif f==4:
                pp=a+up-c; pa=abs(pp-a); pb=abs(pp-up); pc=abs(pp-c)
                pr=a if pa<=pb and pa<=pc else (up if pb<=pc else c)
                line[x]=(line[x]+pr)&255
        rows.append([tuple(line[4*x:4*x+4]) for x in range(w)]); prev=line
    return w,h,rows
