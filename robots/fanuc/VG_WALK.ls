/PROG  VG_WALK
/ATTR
OWNER		= MNEDITOR;
COMMENT		= "vgripd walk";
PROG_SIZE	= 0;
CREATE		= DATE 26-11-25  TIME 12:00:00;
MODIFIED	= DATE 26-11-25  TIME 12:00:00;
FILE_NAME	= ;
VERSION		= 0;
LINE_COUNT	= 20;
MEMORY_SIZE	= 0;
PROTECT		= READ_WRITE;
TCD:  STACK_SIZE	= 0,
      TASK_PRIORITY	= 50,
      TIME_SLICE	= 0,
      BUSY_LAMP_OFF	= 0,
      ABORT_REQUEST	= 0,
      PAUSE_REQUEST	= 0;
DEFAULT_GROUP	= 1,*,*,*,*;
CONTROL_CODE	= 00000000 00000000;
/MN
   1:  !vgripd: hand-eye walk ;
   2:  !UTOOL 10 all 0: the faceplate ;
   3:  UFRAME_NUM=0 ;
   4:  UTOOL_NUM=10 ;
   5:  CALL VGRIPD(0,2) ;
   6:  LBL[1] ;
   7:  IF R[50]=10,JMP LBL[90] ;
   8:  IF (R[50]<>1 AND R[50]<>2),JMP LBL[99] ;
   9:  L PR[50] R[60]mm/sec FINE ;
  10:  WAIT R[61] ;
  11:  PR[51]=LPOS ;
  12:  CALL VGRIPD(0,3) ;
  13:  JMP LBL[1] ;
  14:  LBL[90] ;
  15:  MESSAGE[vgripd_walk_done] ;
  16:  END ;
  17:  LBL[99] ;
  18:  !status in R[50] ;
  19:  MESSAGE[vgripd_walk_stopped] ;
  20:  PAUSE ;
/POS
/END
