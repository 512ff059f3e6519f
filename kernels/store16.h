// STORE16(o, plane, acc): the 16 lanes of a float16 accumulator to 16 images `plane` floats
// apart (o[k * plane] = acc.sk): the batched layout shared by backproject.cl and parallel_beam.cl.
#ifndef CLRECON_STORE16_H
#define CLRECON_STORE16_H
#define STORE16(o, plane, acc)                                                                     \
    o[0 * plane] = acc.s0;  o[1 * plane] = acc.s1;  o[2 * plane] = acc.s2;  o[3 * plane] = acc.s3;    \
    o[4 * plane] = acc.s4;  o[5 * plane] = acc.s5;  o[6 * plane] = acc.s6;  o[7 * plane] = acc.s7;    \
    o[8 * plane] = acc.s8;  o[9 * plane] = acc.s9;  o[10 * plane] = acc.sa; o[11 * plane] = acc.sb;   \
    o[12 * plane] = acc.sc; o[13 * plane] = acc.sd; o[14 * plane] = acc.se; o[15 * plane] = acc.sf;
#endif
