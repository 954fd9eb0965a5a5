# Reconstruct LIBERO-Gen Combination: 11 scenes x 2 picked bowls x 9 places = 200 generated,
# minus 21 dropped training tasks and 5 duplicate instances of held-out combos -> 174 (164 train + 10 test).
import re,collections
PICK={'BPR':'between the plate and the ramekin','TC':'from table center','TD':'in the top drawer of the wooden cabinet','NB':'next to the cookie box','NP':'next to the plate','NR':'next to the ramekin','CB':'on the cookie box','RK':'on the ramekin','ST':'on the stove','WC':'on the wooden cabinet','PL':'on the plate'}
PLACE={'PL':'on the plate','CB':'on the cookie box','RK':'on the ramekin','ST':'on the stove','WC':'on the wooden cabinet','TC':'on the table center','BPR':'between the plate and the ramekin','NP':'next to the plate','NR':'next to the ramekin','NB':'next to the cookie box'}
BOWLAT=dict(PLACE,TD='in the top drawer of the wooden cabinet')
# (bowl_1 location, bowl_2 location); S9 and S10 are the same unordered pair -> keep S9's object order
SCENES={'S1':('BPR','NR'),'S2':('TC','NP'),'S3':('TD','WC'),'S4':('NB','ST'),'S5':('NP','NR'),'S6':('NR','NB'),
        'S7':('CB','WC'),'S8':('RK','CB'),'S9':('ST','WC'),'N1':('TC','PL'),'N2':('PL','NB')}  # N1=S2 with bowl_2 on plate, N2=S6 with bowl_1 on plate
gen=[]
for s,(l1,l2) in SCENES.items():
    for pk,ot,tgt in ((l1,l2,'bowl_2'),(l2,l1,'bowl_1')):
        for q in list(PLACE)+['bowl']:
            if q in (pk,ot): continue
            gen.append(dict(scene=s,pick=pk,other=ot,place=q,key=(tgt if q=='bowl' else q)))
print('generated',len(gen))
HELD=[('S2','TC','CB'),('S3','TD','PL'),('S6','NB','bowl'),('S5','NP','ST'),('S7','CB','bowl'),('S8','CB','WC'),('N1','PL','bowl'),('N2','PL','TC'),('S9','ST','RK'),('S9','WC','BPR')]
heldkeys={(g['pick'],g['key']) for g in gen if (g['scene'],g['pick'],g['place']) in HELD}
DROP={('S1','BPR','NB'),('S3','TD','NB'),('S3','TD','TC'),('N2','NB','bowl'),('S4','NB','bowl'),('S4','NB','NP'),
      ('S2','NP','NB'),('S5','NP','NB'),('S1','NR','NB'),('S5','NR','NB'),('S1','NR','TC'),('S5','NR','TC'),('S6','NR','TC'),
      ('S8','RK','NB'),('S4','ST','bowl'),('S4','ST','PL'),('S3','WC','NB'),('S7','WC','NB'),('S9','WC','NB'),('S3','WC','CB'),('S3','WC','TC')}
test=[g for g in gen if (g['scene'],g['pick'],g['place']) in HELD]
train=[g for g in gen if (g['pick'],g['key']) not in heldkeys and (g['scene'],g['pick'],g['place']) not in DROP]
leak=[g for g in gen if (g['pick'],g['key']) in heldkeys and g not in test]
print('train',len(train),'test',len(test),'total',len(train)+len(test),'held-combo duplicates removed',[(g['scene'],g['pick'],g['place']) for g in leak])
def lang(g): return (PICK[g['pick']], 'in the black bowl '+BOWLAT[g['other']] if g['place']=='bowl' else PLACE[g['place']])
man=collections.Counter()
for p,q in (l.rstrip('\n').split('|') for l in open(__import__('pathlib').Path(__file__).parent.parent.parent / 'tests' / 'data' / 'liberogen_combination_training_tasks.txt')):
    man[(p,re.match(r'(.*?)(?: \d)?$',q).group(1))]+=1
mine=collections.Counter(lang(g) for g in train)
print('train multiset == website manifest:',mine==man)
# The appendix's counts (same pick, same place) per held-out (pick, place key), in the appendix's order.
paper={('TC','CB'):(9,8),('TD','PL'):(7,9),('NB','bowl_1'):(9,4),('NP','ST'):(9,9),('CB','bowl_2'):(9,8),
       ('CB','WC'):(9,8),('PL','bowl_1'):(9,4),('PL','TC'):(9,7),('ST','RK'):(9,9),('WC','BPR'):(8,9)}
for keyname in ('key','locname'):
    ok=0
    for t in test:
        a,b=paper[(t['pick'],t['key'])]
        K=lambda g: g['key'] if keyname=='key' else (('bowl@'+g['other']) if g['place']=='bowl' else g['place'])
        sp={K(g) for g in train if g['pick']==t['pick'] and K(g)!=K(t)}
        sq={g['pick'] for g in train if K(g)==K(t) and g['pick']!=t['pick']}
        ok+=(len(sp)==a)+(len(sq)==b)
        if keyname=='key': print(f"  {t['pick']:>3}->{t['place']:<4}({t['key']:6}) same-pick {len(sp)} (paper {a})  same-place {len(sq)} (paper {b})")
    print(keyname,'matches',ok,'/20')
